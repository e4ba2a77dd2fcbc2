"""The ``colgnn`` command line: a thin shell over the library.

Exit codes: 0 success, 2 bad input (one line on stderr naming the problem).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Callable, Sequence

from colgnn_core.errors import InputError

Handler = Callable[[argparse.Namespace], int]


def _shard(text: str) -> tuple[int, int]:
    """Parse ``I/N`` (0 ≤ I < N)."""
    try:
        i, n = (int(v) for v in text.split("/"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"shard must look like I/N, got {text!r}") from exc
    if not (n >= 1 and 0 <= i < n):
        raise argparse.ArgumentTypeError(f"shard I/N needs 0 <= I < N, got {text!r}")
    return i, n


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def cmd_scenes(args: argparse.Namespace) -> int:
    from colgnn_core.scenes import load_scene, scene_names

    rows = [load_scene(name, args.resolution).to_json() for name in scene_names()]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'scene':<16} {'tool':<9} {'vertices':>8} {'faces':>7}  {'dt':>5}  bbox (m)")
    for r in rows:
        size = [hi - lo for lo, hi in zip(r["object_bbox_min"], r["object_bbox_max"])]
        print(f"{r['name']:<16} {r['tool_shape']:<9} {r['object_vertices']:>8} {r['object_faces']:>7}  {r['dt']:>5.3f}  "
              + " x ".join(f"{s:.3f}" for s in size))
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from colgnn_core.io import read_poses_csv
    from colgnn_core.sim.dataset import generate_dataset

    poses = None
    if args.poses is not None:
        _, poses = read_poses_csv(args.poses)
    manifest = generate_dataset(
        scene_name=args.scene,
        resolution=args.resolution,
        out_dir=Path(args.out),
        sequences=args.sequences,
        test_sequences=args.test_sequences,
        frames=args.frames,
        jobs=args.jobs,
        shard=args.shard,
        poses=poses,
        progress=not args.quiet,
    )
    done = manifest.get("sequences", {})
    print(f"{len(done)} sequence(s) in {args.out} (manifest.json)")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    from colgnn_core.render import render_file

    out = render_file(args.file, args.out, count=args.count, stride=args.stride)
    print(f"wrote {out}")
    return 0


def cmd_ccd_check(args: argparse.Namespace) -> int:
    from colgnn_core.collision.ccd_queries import format_ccd_report, run_ccd_check

    if not Path(args.dir).is_dir():
        raise InputError(f"no such folder: {args.dir}")
    report = run_ccd_check(args.dir)
    print(json.dumps(report, indent=2) if args.json else format_ccd_report(report))
    return 0 if report["false_negatives"] == 0 else 1


def cmd_demo(args: argparse.Namespace) -> int:
    """Ground-truth demo: simulate one short sequence of the default scene and render it."""
    import numpy as np

    from colgnn_core.io import ensure_writable_dir, save_sequence
    from colgnn_core.render import render_strip
    from colgnn_core.scenes import load_scene
    from colgnn_core.scenes.trajectories import sample_poses, split_seeds
    from colgnn_core.sim.dataset import simulate_sequence

    out = ensure_writable_dir(args.out)
    scene = load_scene(args.scene, args.resolution)
    poses = sample_poses(scene, split_seeds("test", 1)[0], args.frames)
    seq = simulate_sequence(scene, poses, progress=True)
    save_sequence(out / "demo_sequence.npz", seq)
    picture = render_strip([seq], [f"{scene.name} (IPC ground truth)"], out / "demo.png", count=5)
    step_ms = float(np.median(seq.extra["step_ms"][1:]))
    print(f"scene {scene.name} ({args.resolution}): {seq.frames} frames, "
          f"{seq.object_positions.shape[1]} object vertices, IPC median {step_ms:.0f} ms/step")
    print(f"wrote {out / 'demo_sequence.npz'} and {picture}")
    return 0


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Handler]]:
    parser = argparse.ArgumentParser(prog="colgnn", description="Collision-aware GNN simulation of tool-object contact.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    handlers: dict[str, Handler] = {}

    p = sub.add_parser("scenes", help="list the scenes")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--resolution", choices=("ci", "full"), default="full")
    handlers["scenes"] = cmd_scenes

    p = sub.add_parser("generate", help="simulate ground-truth sequences with the IPC solver")
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--sequences", type=_positive, default=20, help="training sequences (default 20)")
    p.add_argument("--test-sequences", type=int, default=None, help="held-out test sequences (default: sequences/4, at least 1)")
    p.add_argument("--frames", type=_positive, default=40, help="frames per sequence, rest frame included (default 40)")
    p.add_argument("--jobs", type=_positive, default=1)
    p.add_argument("--shard", type=_shard, default=(0, 1), metavar="I/N", help="simulate only shard I of N")
    p.add_argument("--resolution", choices=("ci", "full"), default="full")
    p.add_argument("--poses", default=None, help="simulate this poses CSV instead of the scene's family")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    handlers["generate"] = cmd_generate

    p = sub.add_parser("render", help="render a sequence or rollout file")
    p.add_argument("file")
    p.add_argument("--out", required=True, help="FILE.png (strip of frames) or FILE.gif (animation)")
    p.add_argument("--count", type=_positive, default=5, help="frames in a PNG strip")
    p.add_argument("--stride", type=_positive, default=1, help="frame stride in a GIF")
    handlers["render"] = cmd_render

    p = sub.add_parser("ccd-check", help="run the collision filter over CCD benchmark CSV queries")
    p.add_argument("dir")
    p.add_argument("--json", action="store_true")
    handlers["ccd-check"] = cmd_ccd_check

    p = sub.add_parser("demo", help="the main job on the default scene")
    p.add_argument("--scene", default="sphere_mat")
    p.add_argument("--resolution", choices=("ci", "full"), default="ci")
    p.add_argument("--frames", type=_positive, default=20)
    p.add_argument("--out", default="out/demo")
    handlers["demo"] = cmd_demo
    return parser, handlers


def main(argv: Sequence[str] | None = None) -> int:
    parser, handlers = build_parser()
    args = parser.parse_args(argv)
    try:
        return handlers[args.command](args)
    except InputError as exc:
        print(f"colgnn {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
