import os
import subprocess
import sys
import time

from colgnn_core.jit_cache import KEEP, source_key, use_source_keyed_cache


def test_the_kernel_cache_folder_changes_with_any_source_and_old_ones_are_pruned(tmp_path, monkeypatch):
    src = tmp_path / "pkg"
    (src / "sub").mkdir(parents=True)
    (src / "a.py").write_text("x = 1\n")
    (src / "sub" / "kernels.py").write_text("def k(): return 1\n")
    (src / "notes.txt").write_text("not a module")
    key = source_key(src)
    assert key == source_key(src) and len(key) == 16
    (src / "notes.txt").write_text("changed, still not a module")
    assert source_key(src) == key
    time.sleep(0.01)
    (src / "sub" / "kernels.py").write_text("def k(): return 2\n")  # a callee in another module changed
    assert source_key(src) != key

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    base = tmp_path / "cache"
    for i in range(KEEP + 2):
        (base / f"old{i}").mkdir(parents=True)
        os.utime(base / f"old{i}", (i, i))
    folder = use_source_keyed_cache(src, base)
    assert folder == base / source_key(src) and folder.is_dir()
    assert os.environ["NUMBA_CACHE_DIR"] == str(folder)
    assert sorted(p.name for p in base.iterdir()) == sorted([folder.name] + [f"old{i}" for i in range(2, KEEP + 2)])

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "mine"))  # the user's own setting wins
    assert use_source_keyed_cache(src, base) is None
    assert os.environ["NUMBA_CACHE_DIR"] == str(tmp_path / "mine")


def test_numba_caches_colgnn_kernels_in_the_source_keyed_folder(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(tmp_path)
    code = ("import numba, colgnn_core.collision.kernels as k, numpy as np; "
            "k.grid_self_join(np.zeros((2, 3)), np.ones((2, 3))); print(numba.config.CACHE_DIR)")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    folder = out.stdout.strip().splitlines()[-1]
    assert folder.startswith(str(tmp_path / "colgnn" / "numba"))
    assert any(p.name.startswith("kernels.grid_self_join") for p in (tmp_path / "colgnn").rglob("*.nbi"))
