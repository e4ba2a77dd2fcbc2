"""The ``colgnn`` command line: a thin shell over the library.

Exit codes: 0 success, 2 bad input (one line on stderr naming the problem).
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
from dataclasses import asdict
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from colgnn_core.collision.ccd_queries import format_ccd_report, run_ccd_check
from colgnn_core.errors import InputError, SimulationError
from colgnn_core.evaluation.accuracy import evaluate, format_markdown
from colgnn_core.evaluation.collision_speed import bench_collision, format_bench_collision
from colgnn_core.evaluation.fit import fit
from colgnn_core.evaluation.frontier import format_frontier, frontier
from colgnn_core.evaluation.model_card import model_cards, models_markdown, write_models_section
from colgnn_core.evaluation.provenance import code_version
from colgnn_core.evaluation.render import render_file, render_scene, render_strip
from colgnn_core.evaluation.report import results
from colgnn_core.evaluation.speed import bench, format_bench
from colgnn_core.evaluation.speed_page import write_speed_page
from colgnn_core.evaluation.stability import format_stability, stability
from colgnn_core.evaluation.stability_page import write_stability_page
from colgnn_core.io import ensure_writable_dir, read_poses_csv, save_sequence
from colgnn_core.learn.train import TrainConfig, train
from colgnn_core.runtime.models import MODEL_DIR
from colgnn_core.runtime.rollout import rollout
from colgnn_core.scenes import SCENE_PATH_ENV, load_scene, scene_dirs, scene_names
from colgnn_core.scenes.custom import MATERIALS, create_scene, format_summary
from colgnn_core.scenes.trajectories import sample_poses, split_seeds
from colgnn_core.sim.dataset import generate_dataset, parse_shard, simulate_sequence
from colgnn_core.sim.partial import PARTIAL_EVERY_S
from colgnn_core.sim.settle import MAX_SAG_FRACTION, check_settle

Handler = Callable[[argparse.Namespace], int]


def _shard(text: str) -> tuple[int, int]:
    """Parse ``I/N`` (0 ≤ I < N) for argparse; the rule lives in ``sim.dataset.parse_shard``."""
    try:
        return parse_shard(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _positive(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _non_negative(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return value


def cmd_scenes(args: argparse.Namespace) -> int:
    rows = [load_scene(name, args.resolution).to_json() for name in scene_names()]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(f"{'scene':<16} {'tool':<9} {'vertices':>8} {'faces':>7}  {'dt':>5}  bbox (m)")
    for r in rows:
        size = [hi - lo for lo, hi in zip(r["object_bbox_min"], r["object_bbox_max"])]
        print(f"{r['name']:<16} {r['tool_shape']:<9} {r['object_vertices']:>8} {r['object_faces']:>7}  "
              f"{r['dt']:>5.3f}  " + " x ".join(f"{s:.3f}" for s in size))
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
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
        split=args.split,
        progress=not args.quiet,
        retry_failed=args.retry_failed,
        dask=args.dask,
        partial_every_s=args.save_every,
    )
    done = manifest.get("sequences", {})
    print(f"{len(done)} sequence(s) in {args.out} (manifest.json)")
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    config = None
    if any(v is not None for v in (args.ccd_form, args.model, args.graph, args.model_options, args.lr,
                                   args.validity_weight)) or args.symmetry:
        config = TrainConfig(symmetry=args.symmetry)
        if args.validity_weight is not None:
            config.w_valid = args.validity_weight
        if args.lr is not None:
            config.lr_init, config.lr_final = args.lr
        if args.graph is not None:
            config.model = {**config.model, "surface_only": args.graph == "surface"}
        if args.ccd_form is not None:
            config.ccd_form = args.ccd_form
        if args.model is not None:
            latent, steps, layers = args.model
            config.model = {**config.model, "latent": latent, "message_passing_steps": steps, "mlp_layers": layers}
        if args.model_options is not None:
            config.model = {**config.model, **args.model_options}
    result = train(args.scene, args.data, args.out, variant=args.variant, resume=args.resume, steps=args.steps,
                   seed=args.seed, threads=args.threads, config=config, resolution=args.resolution,
                   time_budget_s=args.time_budget, progress=not args.quiet, init=args.init)
    print(f"{result.stopped}: step {result.step}/{result.steps} in {result.wall_s:.0f} s -> {result.checkpoint}")
    return 0


def cmd_rollout(args: argparse.Namespace) -> int:
    _, poses = read_poses_csv(args.poses)
    seq = rollout(args.checkpoint or args.scene, poses, correction=not args.no_correction, limits=args.limits,
                  progress=not args.quiet, predictor_options={"self_contact": args.self_contact})
    save_sequence(args.out, seq)
    print(f"wrote {args.out}: {seq.frames} frames")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    if args.stability:
        if args.scene == "all":
            raise InputError("--stability runs one scene at a time (each writes its own row of the page)")
        result = stability(args.checkpoint or args.scene, steps=args.steps, seed=args.seed, threads=args.threads,
                           compile=args.compile, limits=args.limits, rest_relaxation=args.rest_relaxation,
                           self_contact=args.self_contact, progress=not args.json)
        if result["scene"] != args.scene:
            raise InputError(f"checkpoint is for scene {result['scene']!r}, not {args.scene!r}")
        print(json.dumps(result, indent=2) if args.json else format_stability(result))
        if args.markdown:
            print(f"wrote {write_stability_page(result, Path(args.markdown), args.invocation)}")
        return 0
    if args.collision:
        result = bench_collision(args.scene, args.resolution, repeats=args.repeats, sequence=args.sequence)
        print(json.dumps(result, indent=2) if args.json else format_bench_collision(result))
        return 0

    if args.scene == "all" and not args.markdown:
        raise InputError("--scene all needs --markdown FILE (one page for the four scenes)")
    scenes = scene_names() if args.scene == "all" else [args.scene]
    results = []
    for name in scenes:
        result = bench(name, checkpoint=args.checkpoint, frames=args.frames, threads=args.threads,
                       correction=not args.no_correction, progress=not args.json, compile=args.compile,
                       self_contact=args.self_contact, warm_up=not args.cold, rollouts=args.rollouts)
        print(json.dumps(result, indent=2) if args.json else format_bench(result), flush=True)
        results.append(result)
    if args.markdown:
        print(f"wrote {write_speed_page(results, Path(args.markdown), args.invocation)}")
    return 0


def cmd_evaluate(args: argparse.Namespace) -> int:
    if args.all:
        report = results(args.out, scenes=args.scene, data_root=args.data_root, models_dir=args.models,
                         test_sequences=args.test_sequences, frames=args.frames, jobs=args.jobs, threads=args.threads,
                         compile=args.compile, hard_frames=args.hard_frames, random_steps=args.random_steps,
                         progress=not args.quiet)
        print(f"wrote {report.files['markdown']} and {report.files['json']} in {report.wall_s / 60:.1f} min")
        return 0
    if not args.scene or len(args.scene) != 1:
        raise InputError("give one --scene (or --all for the results report)")
    args.scene = args.scene[0]
    if args.frontier:
        ckpts = args.frontier_checkpoints or ([args.checkpoint] if args.checkpoint else [args.scene])
        result = frontier(args.scene, ckpts, args.data, args.out, steps=args.steps,
                          max_sequences=args.max_sequences or 2, threads=args.threads, compile=args.compile,
                          ipc=not args.no_ipc, exact=not args.no_exact, progress=not args.quiet)
        print(format_frontier(result))
        print("wrote " + ", ".join(result["files"].values()))
        return 0

    result = evaluate(args.scene, checkpoint=args.checkpoint, data_dir=args.data, out_dir=args.out,
                      correction_modes=("raw",) if args.no_correction else ("raw", "corrected"),
                      exact=not args.no_exact, max_sequences=args.max_sequences, progress=not args.quiet,
                      command=args.invocation, self_contact=args.self_contact)
    print(format_markdown(result))
    print("wrote " + ", ".join(result["files"].values()))
    return 0


def _model_size(text: str) -> tuple[int, int, int]:
    """Parse ``LATENT/STEPS/LAYERS`` (e.g. 32/5/1)."""
    try:
        values = tuple(int(v) for v in text.split("/"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"model size must look like LATENT/STEPS/LAYERS, got {text!r}") from exc
    if len(values) != 3 or min(values) < 1:
        raise argparse.ArgumentTypeError("model size must be three positive integers LATENT/STEPS/LAYERS, got "
                                         f"{text!r}")
    return values


def cmd_scene(args: argparse.Namespace) -> int:
    """``colgnn scene new``: a scene from a mesh file, its summary and a picture."""
    out = Path(args.out) if args.out else (scene_dirs()[0] if scene_dirs() else Path("scenes"))
    new = create_scene(args.name, args.object, args.size, tool=args.tool, material=args.material, ground=args.ground,
                       out_dir=out, up=args.up, force=args.force,
                       check=lambda scene: check_settle(scene, args.max_sag).line())
    print(format_summary(new))
    picture = render_scene(new.scene, new.toml.with_name(f"{new.name}-scene.png"))
    print(f"wrote {', '.join(str(f) for f in new.files)} and {picture}")
    if new.toml.parent.resolve() not in [d.resolve() for d in scene_dirs()]:
        print(f"to use it: export {SCENE_PATH_ENV}={new.toml.parent.resolve()}")
    return 0


def cmd_fit(args: argparse.Namespace) -> int:
    result = fit(args.name, resolution=args.resolution, minutes=args.minutes, jobs=args.jobs, dask=args.dask,
                 progress=not args.quiet, invocation=args.invocation)
    print(f"{result.name} ({result.resolution}) in {result.wall_s / 60:.1f} min: wrote {result.model}, "
          f"{result.report} and {result.picture}")
    rel = result.metrics["relative"]
    print("held-out relative displacement error (all vertices): model + correction "
          f"{rel['corrected']['all']['mean']:.3f}, rest {rel['rest']['all']['mean']:.3f}, rest + correction "
          f"{rel['rest_correction']['all']['mean']:.3f}; intersecting frames "
          f"{result.metrics['rows']['corrected']['collisions']['intersecting_frames']}")
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    out = render_file(args.file, args.out, count=args.count, stride=args.stride)
    print(f"wrote {out}")
    return 0


def cmd_ccd_check(args: argparse.Namespace) -> int:
    if not Path(args.dir).is_dir():
        raise InputError(f"no such folder: {args.dir}")
    report = run_ccd_check(args.dir)
    print(json.dumps(report, indent=2) if args.json else format_ccd_report(report))
    return 0 if report["false_negatives"] == 0 else 1


def cmd_models(args: argparse.Namespace) -> int:
    folder = Path(args.dir) if args.dir else MODEL_DIR
    if not folder.is_dir():
        raise InputError(f"no such models folder: {folder}")
    if args.markdown:
        print(f"wrote {write_models_section(folder, args.markdown, args.invocation)}")
        return 0
    cards = model_cards(folder)
    print(json.dumps([asdict(c) for c in cards], indent=2) if args.json else models_markdown(cards, args.invocation))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Ground-truth demo: simulate one short sequence of the default scene and render it."""
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


def _add_scenes(sub) -> None:
    p = sub.add_parser("scenes", help="list the scenes")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--resolution", choices=("ci", "full"), default="full")


def _add_generate(sub) -> None:
    p = sub.add_parser("generate", help="simulate ground-truth sequences with the IPC solver")
    p.add_argument("--scene", required=True)
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--sequences", type=_positive, default=20,
                   help="training sequences (default 20); with --split test: test sequences")
    p.add_argument("--split", choices=("both", "train", "test"), default="both",
                   help="both (default): --sequences training + --test-sequences held-out ones; or only one split")
    p.add_argument("--test-sequences", type=int, default=None,
                   help="held-out test sequences (default: sequences/4, at least 1)")
    p.add_argument("--frames", type=_positive, default=40, help="frames per sequence, rest frame included (default 40)")
    p.add_argument("--jobs", type=_positive, default=1, help="local solver processes")
    p.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="simulate on a Dask cluster: its scheduler (tcp://HOST:8786), or local:N worker processes here")
    p.add_argument("--shard", type=_shard, default=(0, 1), metavar="I/N", help="simulate only shard I of N")
    p.add_argument("--resolution", choices=("ci", "full"), default="full")
    p.add_argument("--poses", default=None, help="simulate this poses CSV instead of the scene's family")
    p.add_argument("--save-every", type=float, default=PARTIAL_EVERY_S, metavar="SECONDS",
                   help="save each sequence in progress to FILE.partial this often; an interrupted run continues "
                        f"from it (default {PARTIAL_EVERY_S:g})")
    p.add_argument("--retry-failed", action="store_true",
                   help="simulate again sequences whose every seed failed in an earlier run (default: skip them)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _learning_rates(text: str) -> tuple[float, float]:
    """``INIT[:FINAL]`` -> (lr_init, lr_final), both > 0; FINAL defaults to INIT / 100 (the default schedule's
    ratio)."""
    parts = text.split(":")
    try:
        rates = [float(v) for v in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected INIT or INIT:FINAL (numbers), got {text!r}") from None
    if len(rates) not in (1, 2) or not all(math.isfinite(r) and r > 0 for r in rates):
        raise argparse.ArgumentTypeError(f"expected INIT or INIT:FINAL, each a number > 0, got {text!r}")
    return rates[0], rates[1] if len(rates) == 2 else rates[0] / 100.0


def _json_object(text: str) -> dict:
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise argparse.ArgumentTypeError(f"not JSON: {exc}") from exc
    if not isinstance(value, dict):
        raise argparse.ArgumentTypeError("expected a JSON object, e.g. '{\"order\": 0}'")
    return value


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train a model on a generated dataset")
    p.add_argument("--scene", required=True)
    p.add_argument("--data", required=True, help="dataset folder made by `colgnn generate`")
    p.add_argument("--out", required=True, help="checkpoint file (.pt), written atomically every N steps")
    p.add_argument("--variant", choices=("full", "baseline", "no-compact", "subspace"), default="full")
    p.add_argument("--resume", action="store_true", help="continue the run stored in --out")
    p.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="fine-tune: start from this checkpoint's network (same scene; its size and settings) "
                        "instead of random weights")
    p.add_argument("--steps", type=_positive, default=None, help="total training steps")
    p.add_argument("--graph", choices=("surface", "tet"), default=None,
                   help="graph nodes: surface vertices only, or every tet-mesh vertex (default: the scene's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=_positive, default=None, help="torch threads")
    p.add_argument("--model", type=_model_size, default=None, metavar="L/S/M",
                   help="latent/message-passing steps/MLP layers")
    p.add_argument("--model-options", type=_json_object, default=None, metavar="JSON",
                   help='more model settings (learn.model.ModelConfig), e.g. \'{"order": 0, "quasi_static": true, '
                        '"coarse_nodes": 32, "coarse_steps": 3}\'')
    p.add_argument("--ccd-form", choices=("max", "mean", "sum_squares"), default=None,
                   help="reduction of L_ccd (paper: max)")
    p.add_argument("--lr", type=_learning_rates, default=None, metavar="INIT[:FINAL]",
                   help="learning rate at the start and at the end of the exponential decay (default 1e-3:1e-5; "
                        "FINAL defaults to INIT/100). A fine-tune (--init) usually wants a lower INIT")
    p.add_argument("--symmetry", action="store_true",
                   help="turn each sample by a random rotation of the scene's declared [symmetry] (knife_torus)")
    p.add_argument("--validity-weight", type=_non_negative, default=None, metavar="W",
                   help="weight of L_valid: each predicted surface triangle within 84 degrees of flipping against its "
                        "rest orientation costs (0.1 - cos) x W (default 0: off)")
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="stop (with a checkpoint) after this long")
    p.add_argument("--resolution", choices=("ci", "full"), default=None, help="default: from the dataset manifest")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _add_rollout(sub) -> None:
    p = sub.add_parser("rollout", help="roll a model out over a poses CSV")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint")
    src.add_argument("--scene", help="use the shipped model of this scene")
    p.add_argument("--poses", required=True, help="CSV with t,px,py,pz,qx,qy,qz,qw")
    p.add_argument("--out", required=True, help="rollout .npz")
    p.add_argument("--no-correction", action="store_true",
                   help="the raw network, without the collision-aware correction")
    p.add_argument("--limits", choices=("none", "data"), default="none",
                   help="'data': cap per-step motion and distance from rest by the training data's extremes (counted)")
    _add_self_contact(p, "with the correction")
    p.add_argument("--quiet", action="store_true")


def _add_self_contact(p: argparse.ArgumentParser, what: str) -> None:
    """``--self-contact`` / ``--no-self-contact``: the Predictor's self-contact stage; absent: the scene's default."""
    p.add_argument("--self-contact", action=argparse.BooleanOptionalAction, default=None,
                   help=f"run the Predictor's self-contact stage, or not ({what}); default: the scene's "
                        "[correction] self_contact, as the node runs it")


def _add_bench(sub) -> None:
    p = sub.add_parser("bench", help="Predictor step time vs the IPC solver on the same poses, in one run")
    p.add_argument("--scene", required=True, help="a scene, or 'all' (with --markdown)")
    p.add_argument("--checkpoint", default=None, help="default: the shipped model of the scene")
    p.add_argument("--frames", type=_positive, default=40, help="trajectory length, rest frame included")
    p.add_argument("--markdown", default=None, metavar="FILE",
                   help="also write the results as a page: the speed page (docs/SPEED.md) and FILE's "
                        "folder/bench/<scene>.json; with --stability, FILE's folder/<scene>.json and the stability "
                        "table in FILE (docs/stability/README.md)")
    p.add_argument("--threads", type=_positive, default=2, help="torch threads of the Predictor")
    p.add_argument("--no-correction", action="store_true", help="time the raw network only")
    p.add_argument("--compile", action="store_true", help="torch.compile the network first (faster steps)")
    p.add_argument("--rollouts", type=_positive, default=1,
                   help="timed passes over the trajectory (statistics over all their steps; the page gives the range "
                        "of each pass's median)")
    p.add_argument("--cold", action="store_true",
                   help="time the Predictor without the warm-up that the node runs before it serves")
    _add_self_contact(p, "its time is self_contact_ms")
    p.add_argument("--collision", action="store_true",
                   help="instead: collision detection (broad + filter + narrow) vs ipctk's CCD on one contact step")
    p.add_argument("--resolution", default="full", help="with --collision: scene resolution (full or ci)")
    p.add_argument("--sequence", default=None,
                   help="with --collision: take the deepest-contact step of this sequence file (default: synthetic)")
    p.add_argument("--repeats", type=_positive, default=50, help="with --collision: timed repeats")
    p.add_argument("--stability", action="store_true",
                   help="instead: a long random-motion rollout, then the tool leaves: intersections, memory, "
                        "return to rest")
    p.add_argument("--steps", type=_positive, default=10_000, help="with --stability: random-motion steps")
    p.add_argument("--seed", type=int, default=0, help="with --stability: seed of the random motion")
    p.add_argument("--limits", choices=("none", "data"), default="none",
                   help="with --stability: cap the network output by the training data's extremes")
    p.add_argument("--rest-relaxation", type=float, default=0.0,
                   help="with --stability: pull the object back towards rest by this fraction per step while the "
                        "tool is out of reach (see Predictor)")
    p.add_argument("--json", action="store_true")


def _add_evaluate(sub) -> None:
    p = sub.add_parser("evaluate", help="rollout accuracy and collision metrics on a dataset's test sequences")
    p.add_argument("--scene", action="append", default=None,
                   help="the scene (with --all: repeat to choose scenes; default all)")
    p.add_argument("--checkpoint", default=None, help="default: the shipped model of the scene")
    p.add_argument("--data", default=None, help="dataset folder with test_XXXX.npz (made by `colgnn generate`)")
    p.add_argument("--out", required=True, help="output folder: metrics.json, metrics.md, rmse_over_time.png")
    p.add_argument("--no-exact", action="store_true", help="crossings by the narrow phase instead of the exact CCD")
    p.add_argument("--no-correction", action="store_true", help="evaluate the raw network only")
    p.add_argument("--max-sequences", type=_positive, default=None, help="only the first N test sequences")
    _add_self_contact(p, "in every corrected rollout")
    p.add_argument("--quiet", action="store_true", help="no per-sequence lines")
    p.add_argument("--frontier", action="store_true",
                   help="instead: speed against error of --checkpoints (raw and corrected) and the IPC solver "
                        "at 3 settings, on the same test poses: frontier.json/.md/.png")
    p.add_argument("--checkpoints", dest="frontier_checkpoints", nargs="+", default=None,
                   help="with --frontier: the GNN checkpoints (default: --checkpoint or the shipped model)")
    p.add_argument("--steps", type=_positive, default=40, help="with --frontier: rollout steps (default 40)")
    p.add_argument("--threads", type=_positive, default=2, help="with --frontier or --all: torch threads (default 2)")
    p.add_argument("--compile", action="store_true", help="with --frontier or --all: torch.compile the networks")
    p.add_argument("--no-ipc", action="store_true", help="with --frontier: leave out the solver points")
    p.add_argument("--all", action="store_true",
                   help="instead: the results report (RESULTS.md, results.json, img/) of every scene's shipped "
                        "models into --out, on freshly simulated test data (`make results`)")
    p.add_argument("--data-root", default="data/results", help="with --all: test data folder (resumable)")
    p.add_argument("--models", default=None, help="with --all: checkpoint folder (default: the shipped models)")
    p.add_argument("--test-sequences", type=_positive, default=2, help="with --all: test sequences per scene")
    p.add_argument("--frames", type=_positive, default=51, help="with --all: frames per test sequence")
    p.add_argument("--jobs", type=_positive, default=2, help="with --all: solver processes for the test data")
    p.add_argument("--hard-frames", type=_positive, default=40, help="with --all: length of the short hard cases")
    p.add_argument("--random-steps", type=int, default=2000,
                   help="with --all: steps of the random motion with tilts (0: leave it out)")


def _add_scene(sub) -> None:
    p = sub.add_parser("scene", help="make your own scene: `colgnn scene new NAME --object MESH --size M --tool T`")
    verbs = p.add_subparsers(dest="scene_command", required=True, metavar="VERB")
    n = verbs.add_parser("new", help="a scene from a mesh file and a tool shape (written as NAME.toml + assets)")
    n.add_argument("name", help="scene name (letters, digits, '_' or '-')")
    n.add_argument("--object", required=True, metavar="MESH", help="closed surface: .obj, .stl, .ply or .msh")
    n.add_argument("--size", required=True, type=float, metavar="METRES", help="longest side of the object (m)")
    n.add_argument("--tool", required=True, metavar="SHAPE[:key=value,...]",
                   help="sphere, cylinder, cone or blade, sizes optional (m), e.g. sphere:radius=0.02")
    n.add_argument("--material", default="rubber", metavar="PRESET|E,nu,rho",
                   help=f"{', '.join(MATERIALS)} (default rubber), or Young's modulus (Pa), Poisson ratio, density")
    n.add_argument("--ground", action="store_true",
                   help="rest the object on a ground plane (default: glue its bottom band in place)")
    n.add_argument("--max-sag", type=float, default=MAX_SAG_FRACTION, metavar="FRACTION",
                   help="refuse an object that sags more than this fraction of its height while it settles under "
                        f"gravity (default {MAX_SAG_FRACTION}; checked at ci with the ground-truth solver)")
    n.add_argument("--up", choices=("x", "y", "z", "-x", "-y", "-z"), default=None,
                   help="the file's up axis (default: z for .stl, y for .obj/.ply/.msh)")
    n.add_argument("--out", default=None, metavar="DIR",
                   help=f"scene folder (default: the first folder of {SCENE_PATH_ENV}, else ./scenes)")
    n.add_argument("--force", action="store_true", help="replace an existing scene of that name")


def _add_fit(sub) -> None:
    p = sub.add_parser("fit", help="generate -> train -> evaluate your scene within a time budget (resumable)")
    p.add_argument("name", help=f"a scene made by `colgnn scene new` (found through {SCENE_PATH_ENV})")
    p.add_argument("--resolution", choices=("ci", "full"), default="ci")
    p.add_argument("--minutes", type=float, default=30.0, help="time budget (default 30)")
    p.add_argument("--jobs", type=_positive, default=1, help="local solver processes")
    p.add_argument("--dask", default=None, metavar="ADDRESS",
                   help="simulate on a Dask cluster: its scheduler (tcp://HOST:8786), or local:N worker processes here")
    p.add_argument("--quiet", action="store_true", help="no progress display")


def _add_render(sub) -> None:
    p = sub.add_parser("render", help="render a sequence or rollout file")
    p.add_argument("file")
    p.add_argument("--out", required=True, help="FILE.png (strip of frames) or FILE.gif (animation)")
    p.add_argument("--count", type=_positive, default=5, help="frames in a PNG strip")
    p.add_argument("--stride", type=_positive, default=1, help="frame stride in a GIF")


def _add_ccd_check(sub) -> None:
    p = sub.add_parser("ccd-check", help="run the collision filter over CCD benchmark CSV queries")
    p.add_argument("dir")
    p.add_argument("--json", action="store_true")


def _add_demo(sub) -> None:
    p = sub.add_parser("demo",
                       help="ground-truth demo: simulate and render a short sequence with the IPC solver (no model)")
    p.add_argument("--scene", default="sphere_mat")
    p.add_argument("--resolution", choices=("ci", "full"), default="ci")
    p.add_argument("--frames", type=_positive, default=20)
    p.add_argument("--out", default="out/demo")


def _add_models(sub) -> None:
    p = sub.add_parser("models", help="the shipped checkpoints: scene, size, training data and steps (from the files)")
    p.add_argument("--dir", default=None, help="checkpoint folder (default: the shipped models)")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    p.add_argument("--markdown", default=None, metavar="FILE",
                   help="write the table into FILE between its <!-- begin models --> / <!-- end models --> markers")


# (verb, parser set-up, handler), in the order of `colgnn --help`
VERBS = (
    ("scenes", _add_scenes, cmd_scenes),
    ("scene", _add_scene, cmd_scene),
    ("generate", _add_generate, cmd_generate),
    ("train", _add_train, cmd_train),
    ("rollout", _add_rollout, cmd_rollout),
    ("bench", _add_bench, cmd_bench),
    ("evaluate", _add_evaluate, cmd_evaluate),
    ("fit", _add_fit, cmd_fit),
    ("render", _add_render, cmd_render),
    ("ccd-check", _add_ccd_check, cmd_ccd_check),
    ("models", _add_models, cmd_models),
    ("demo", _add_demo, cmd_demo),
)


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Handler]]:
    parser = argparse.ArgumentParser(prog="colgnn",
                                     description="Collision-aware GNN simulation of tool-object contact.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for _, add, _ in VERBS:
        add(sub)
    return parser, {name: handler for name, _, handler in VERBS}


def main(argv: Sequence[str] | None = None) -> int:
    parser, handlers = build_parser()
    args = parser.parse_args(argv)
    args.invocation = "colgnn " + " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
    code_version()  # pinned now: the pages a long run writes at its end name the code it started with
    try:
        return handlers[args.command](args)
    except InputError as exc:
        print(f"colgnn {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except SimulationError as exc:  # the solver could not verify a frame; the other sequences were written
        print(f"colgnn {args.command}: simulation failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
