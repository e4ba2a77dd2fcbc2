"""The results report as typed data: what :mod:`.report` measures, :mod:`.report_markdown` writes, and
``docs/results.json`` holds (:meth:`ResultsReport.to_dict` / :meth:`ResultsReport.from_dict` give and read that
file's JSON, key for key), plus the rows of the tables and the paper's figures they are compared with.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass, field

# Rows of the tables: (key in SceneResults.rows, label). "shipped" rows exist where the scene's default model is
# not the paper's full variant (report.model_paths); the row of the default model with the correction is marked
# "(colgnn)" (SceneResults.colgnn_key).
# Rows of the relative-error table (key, label): each variant's raw network, the full and the shipped model
# corrected, the shipped one as the node runs it, then the two trivial baselines (issue: "every accuracy table
# carries two trivial baselines").
RELATIVE_ROWS = (("subspace", "subspace (Holden et al. 2019), raw"), ("baseline", "MeshGraphNets baseline, raw"),
                 ("no-compact", "ours without L_compact, raw"), ("full", "ours, raw network"),
                 ("full+correction", "ours + correction (no caps, no rest relaxation)"),
                 ("shipped", "shipped model, raw network"),
                 ("shipped+correction", "shipped model + correction (no caps, no rest relaxation)"),
                 ("node", "the shipped model as the node runs it (caps + rest relaxation)"),
                 ("rest", "rest (nothing moves)"), ("rest+correction", "rest + correction (no network)"))
ROWS = (("ground_truth", "ground truth (IPC)"), ("subspace", "subspace (Holden et al. 2019)"),
        ("baseline", "baseline (MeshGraphNets)"), ("no-compact", "no-compact (ablation)"),
        ("full", "full (paper method)"), ("full+correction", "full + correction"),
        ("shipped", "shipped model"), ("shipped+correction", "shipped model + correction"))
OPTIONAL_ROWS = ("shipped", "shipped+correction")  # only where the scene ships a model apart from the paper's
CROSSING_KEYS = ("N_vf", "d_vf_mean", "d_vf_max", "N_ee", "d_ee_mean", "d_ee_max")

PAPER_HARDWARE = "Intel Xeon E5-2637, 128 GB RAM, GTX 1080 Ti (network on the GPU; IPC on the CPU)"
# The paper's Table 1 (its mesh sizes, IPC ms per step, its method's ms per step, speedup).
PAPER_TABLE1 = {
    "cone_bunny": {"vertices": 3022, "edges": 9054, "faces": 6036, "ipc_ms": 2070, "ms": 75, "speedup": 27.60},
    "knife_torus": {"vertices": 5926, "edges": 17772, "faces": 11848, "ipc_ms": 6380, "ms": 60, "speedup": 127.60},
    "sphere_mat": {"vertices": 4439, "edges": 13305, "faces": 8870, "ipc_ms": 2440, "ms": 135, "speedup": 18.07},
    "cylinder_banana": {"vertices": 3607, "edges": 10809, "faces": 7206, "ipc_ms": 1200, "ms": 90, "speedup": 13.33},
}
# The paper's Table 2: reduction (%) of its method relative to the MeshGraphNets baseline, per collision type
# (vertex-face: cone-bunny, edge-face: knife-torus, face-face: sphere-mat and cylinder-banana).
PAPER_TABLE2 = {
    "cone_bunny": {"N_vf": 69.61, "d_vf_mean": 72.23, "d_vf_max": 69.63},
    "knife_torus": {"N_vf": 62.50, "d_vf_mean": 53.67, "d_vf_max": 49.84},
    "sphere_mat": {"N_vf": 58.15, "d_vf_mean": 58.16, "d_vf_max": 59.51, "N_ee": 34.46, "d_ee_mean": 42.22,
                   "d_ee_max": 45.22},
    "cylinder_banana": {"N_vf": 58.15, "d_vf_mean": 58.16, "d_vf_max": 59.51, "N_ee": 34.46, "d_ee_mean": 42.22,
                        "d_ee_max": 45.22},
}

OMIT_NONE = {"omit_none": True}  # field metadata: the key is left out of the JSON when the value is None


class Record:
    """A dataclass that converts to and from the report's JSON, fields in order (nested records included)."""

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None and f.metadata.get("omit_none"):
                continue
            out[f.name] = _plain(value)
        return out

    @classmethod
    def from_dict(cls, data: dict):
        hints = typing.get_type_hints(cls)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown keys {sorted(unknown)}")
        return cls(**{k: _typed(v, hints[k]) for k, v in data.items()})


def _plain(value):
    if isinstance(value, Record):
        return value.to_dict()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def _typed(value, hint):
    """``value`` (from JSON) as the type ``hint``: records, dicts and lists of them, optional ones."""
    if value is None:
        return None
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        records = [a for a in args if isinstance(a, type) and issubclass(a, Record)]
        if len(records) > 1:  # a union of records: the one whose fields match the keys
            return next(r for r in records if set(value) <= {f.name for f in dataclasses.fields(r)}).from_dict(value)
        inner = [a for a in args if a is not type(None)]
        return _typed(value, inner[0]) if len(inner) == 1 else value
    if origin is dict:
        return {k: _typed(v, args[1]) for k, v in value.items()}
    if origin is list:
        return [_typed(v, args[0]) for v in value]
    if isinstance(hint, type) and issubclass(hint, Record):
        return hint.from_dict(value)
    return value


@dataclass
class Stat(Record):
    """Median and p95 (ms) of per-step times (:func:`colgnn_core.evaluation.measure.stats`)."""

    median: float
    p95: float


@dataclass
class MeanStd(Record):
    """Mean ± std over the test sequences (None, None, 0 when there are none)."""

    mean: float | None
    std: float | None
    n: int


@dataclass
class RmseCurve(Record):
    """Per-step RMSE fraction: mean and std over the sequences that reach the step, and how many do."""

    mean: list[float]
    std: list[float]
    n: list[int]


@dataclass
class RmseSummary(Record):
    """Rollout RMSE as a fraction of the bbox diagonal at steps 1, 10, 50 and over all steps."""

    step_1: MeanStd
    step_10: MeanStd
    step_50: MeanStd
    all: MeanStd
    curve: RmseCurve


@dataclass
class CollisionSummary(Record):
    """Crossings and penetrations pooled over the test sequences
    (:func:`colgnn_core.evaluation.measure.collision_aggregate`)."""

    steps: int
    frames: int
    N_vf: float
    N_vf_total: int
    N_vf_max: int
    d_vf_mean: float
    d_vf_max: float
    N_ee: float
    N_ee_total: int
    N_ee_max: int
    d_ee_mean: float
    d_ee_max: float
    intersecting_frames: int
    intersecting_frames_fraction: float
    object_vertices_inside_total: int
    object_vertices_inside_max: int
    tool_vertices_inside_total: int
    tool_vertices_inside_max: int
    intersecting_triangle_pairs_total: int
    intersecting_triangle_pairs_max: int


@dataclass
class SurfaceCounts(Record):
    """Object-alone validity of the checked frames (:func:`colgnn_core.evaluation.accuracy.surface_checks`)."""

    checked_frames: int
    self_intersecting_frames: int
    invalid_face_frames: int
    frames: int = 0                   # every frame, for the validity test alone (0: a report from before it)
    invalid_face_frames_all: int = 0


@dataclass
class Row(Record):
    """One row of Table 2 and the accuracy table (``rmse`` is None for the ground truth)."""

    rmse: RmseSummary | None
    collisions: CollisionSummary
    surface: SurfaceCounts | None = field(default=None, metadata=OMIT_NONE)


@dataclass
class SpeedRow(Record):
    """Table 1: the Predictor and the solver timed on the same poses in one run."""

    vertices: int
    surface_vertices: int
    edges: int
    faces: int
    ipc_ms: Stat
    raw_ms: Stat              # the step without the correction stage
    total_ms: Stat            # the whole published step
    graph_ms: Stat
    gnn_ms: Stat
    correction_ms: Stat
    speedup_vs_ipc: float     # IPC median / total median
    steps: int
    load_average_1min: float
    ipc_load_average_1min: float
    threads: int
    compiled: bool


@dataclass
class HardCase(Record):
    """One hard-case trajectory through the Predictor, checked by ipctk
    (:func:`colgnn_core.evaluation.stability.check_rollout`); a non-finite run has only ``error``."""

    steps: int | None = field(default=None, metadata=OMIT_NONE)
    checked: int | None = field(default=None, metadata=OMIT_NONE)
    intersecting: int | None = field(default=None, metadata=OMIT_NONE)
    crossing: int | None = field(default=None, metadata=OMIT_NONE)
    contact: int | None = field(default=None, metadata=OMIT_NONE)
    fallback_steps: int | None = field(default=None, metadata=OMIT_NONE)
    before: int | None = field(default=None, metadata=OMIT_NONE)
    after_nonzero: int | None = field(default=None, metadata=OMIT_NONE)
    substeps: int | None = field(default=None, metadata=OMIT_NONE)
    fallbacks_total: int | None = field(default=None, metadata=OMIT_NONE)
    finite: bool = False
    error: str | None = field(default=None, metadata=OMIT_NONE)
    wall_s: float = 0.0


@dataclass
class FrontierPoint(Record):
    """One method on the speed/error plane (:mod:`colgnn_core.evaluation.frontier`)."""

    label: str
    kind: str                 # 'raw' | 'corrected' | 'baseline' | 'ipc'
    ms_median: float
    rmse_last: float
    rmse_last_std: float
    crossings: int
    intersecting_frames: int
    relative: float | None = field(default=None, metadata=OMIT_NONE)          # relative error, all vertices
    relative_contact: float | None = field(default=None, metadata=OMIT_NONE)  # the same, contact region


@dataclass
class FrontierResult(Record):
    """The content of ``frontier.json``."""

    scene: str
    resolution: str
    steps: int
    threads: int
    compiled: bool
    exact: bool
    sequences: list[str]
    ipc_sequences: list[str]
    cpu_count: int | None
    load_average_1min: float | None
    points: list[FrontierPoint]
    wall_s: float
    files: dict[str, str] = field(default_factory=dict)


@dataclass
class FrontierSection(Record):
    result: FrontierResult
    plot: str                 # the picture copied into img/


@dataclass
class Pictures(Record):
    errors: str               # RMSE over time of every row
    comparison: str           # ground truth / baseline / colgnn strip
    ablation: str | None = field(default=None, metadata=OMIT_NONE)  # full vs no-compact strip


@dataclass
class SceneResults(Record):
    """Everything the report says about one scene."""

    scene: str
    resolution: str
    data_dir: str
    resumed_sequences: int
    solver_failures: str
    checkpoints: dict[str, str]
    model_sizes: dict[str, str]
    test_data_s: float
    speed: SpeedRow
    speed_s: float
    sequences: list[str]
    frames: list[int]
    evaluate_s: float
    rows: dict[str, Row]
    pictures: Pictures
    hard_cases: dict[str, HardCase]
    hard_cases_s: float
    frontier: FrontierSection | None = field(default=None, metadata=OMIT_NONE)
    # relative displacement error (all vertices, contact region) by row key of RELATIVE_ROWS
    relative: dict[str, dict[str, MeanStd]] = field(default_factory=dict)

    def colgnn_key(self) -> str:
        """The row of the scene's default model with the correction: what colgnn publishes."""
        return "shipped+correction" if "shipped+correction" in self.rows else "full+correction"

    def size(self, key: str) -> str:
        """latent/MP steps/MLP layers of the checkpoint of row ``key`` ('' for models without a graph network)."""
        return self.model_sizes.get(key.replace("+correction", ""), "")


@dataclass
class SkippedScene(Record):
    scene: str
    skipped: str              # why (no shipped full model)


@dataclass
class Machine(Record):
    cpu: str
    cores: int | None
    python: str
    torch: str


@dataclass
class Settings(Record):
    test_sequences: int
    frames: int
    threads: int
    compile: bool
    hard_frames: int
    random_steps: int


@dataclass
class ResultsReport(Record):
    """The whole report (``results.json``); ``files`` (the paths written) is set after writing."""

    generated: str
    machine: Machine
    settings: Settings
    scenes: dict[str, SceneResults | SkippedScene]
    wall_s: float = 0.0
    files: dict[str, str] | None = field(default=None, metadata=OMIT_NONE)
    code: str = ""  # the code version measured (provenance.code_version), "" in reports older than the field

    def measured(self) -> dict[str, SceneResults]:
        """The scenes that were measured (not skipped), in report order."""
        return {n: s for n, s in self.scenes.items() if isinstance(s, SceneResults)}
