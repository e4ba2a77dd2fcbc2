"""IPC ground-truth time stepper on ipctk (Li et al. 2020, "Incremental Potential Contact").

One step of implicit Euler minimises the incremental potential::

    E(x) = ½‖x − x̃‖²_M + h²·Ψ_SNH(x) + κ·B(x) + D(x) [+ tool penalty],   x̃ = xⁿ + h·vⁿ + h²·g,

over the object vertices (and, in phase 1 below, the tool vertices), with projected
Newton (per-element PSD projection, sparse Cholesky) and a line search whose first
trial step is capped by ipctk's CCD (AdditiveCCD: robust and fast on flat-on-flat
contact) and by a tet-inversion guard, then halved until the energy decreases.

* B: ipctk's clamped-log barrier over two CollisionMeshes built with
  ``build_from_full_mesh`` (interior object vertices never collide): object–tool pairs
  (a patch filter drops object–object and tool–tool pairs) with the gap ``dmin``, and the
  object's self-contact without a gap (rest meshes can have non-adjacent surface elements
  closer than dmin, e.g. the bunny's ears); plus an analytic point–plane barrier (same function of squared
  distance, same κ) between the object's surface vertices and the ground
  ``z = scene.ground_height``, with an analytic CCD clamp. (ipctk 1.6.1's own planes
  only collect plane–vertex pairs within about dhat/2 while the barrier reaches dhat: the
  energy jumps, which breaks the line search.) The kinematic tool ignores the ground.
* Minimum object–tool gap ``dmin`` (IPC's offset barrier; it acts on [dmin, dmin + dhat]).
  The Newton path is collision-free by CCD, but the contract also wants the *straight*
  frame-to-frame motion to be crossing-free; a chord of a surface sliding round a curved
  tool sags inside it unless the gap exceeds that sag. Measured on the 'ci' scenes (coarse
  faces, sharp cone tip): dmin = 2·dhat still failed 2 of 6 bunny sequences (a dent snapping
  back past the tip, faces moving 2 cm in a frame); 4·dhat passed them. Default 4·dhat
  (≈ 0.9–1.7 mm on these scenes). The gap makes a recorded path (below) rare, not impossible.
* D: IPC's lagged friction with ``scene.friction`` as μ (0 = off): ipctk
  TangentialCollisions + FrictionPotential for object–tool/self contact, and the same
  smoothed Coulomb model (f0 mollifier, ε_v·h) written out for the ground plane. Normal
  forces and tangent bases are lagged from the start of the step (``friction_iterations``
  adds re-lagged solves).
* κ: ``ipctk.initial_barrier_stiffness`` at every step (kept if the previous step's κ
  is larger), then ``ipctk.update_barrier_stiffness`` after every Newton iteration.
* Stop when ‖p‖_∞ < newton_tol · bbox_diagonal · h (IPC's rule).
* The Newton system is solved by conjugate gradients with a Jacobi preconditioner, and once that fails, by CG
  preconditioned with a lagged sparse Cholesky factor, refreshed when it stops converging (``sim.linear_solve``).
  On the soft scenes the mass term M/h² makes the projected Hessian strongly diagonal and Jacobi CG always
  converges; on the stiff bunny it does not. The converged state is the same to the Newton tolerance: only the
  search directions differ (relative 1e-5).

**Driving the kinematic tool.** The tool's surface vertices are extra degrees of
freedom. Phase 1 pulls them towards their targets with a stiff mass-weighted quadratic
penalty (k·m̄/2)‖x_t − x_t^target‖², solved jointly with the object, so the CCD line
search covers the combined motion and the energy decreases monotonically even for
large tool motions. Phase 2 fixes the tool: its small remaining residual (force/k)
is applied as a prescribed (Dirichlet) step whose object response solves
H_ff p_f = −(g_f + H_ft p_t); that combined step is CCD-clamped too. The tool ends
*exactly* on its target; if it cannot get there, :class:`SimulationError`.

**Sub-frames.** A frame whose solve fails (Newton does not converge, the tool cannot reach
its target, the new state does not verify) is solved again as two sub-frames of dt/2 with
the tool at the slerp midpoint, recursively, down to 2^MAX_SUBFRAME_DEPTH = 16 sub-frames
(the Predictor's substep limit), so every trajectory the Predictor accepts can be tried.

**Verification** of every state (frame or sub-frame end): ``ipctk.has_intersections`` is
false (object–tool and self), no object vertex is at or below the ground, every tet has
J > 0, Newton converged and the tool sits exactly on its target. Of every frame's motion:
the straight motion from the previous frame is collision-free by ``ipctk.is_step_collision_free``
(Tight-Inclusion, tolerance 1e-6): object–tool pairs with its default line-search clearance
(the criterion the Predictor's published steps meet), object self-contact for a real touch.
Where the straight motion fails, the motion between the two frames is the piecewise-linear
path through intermediate solver states, every piece passing the same check; the sequence
file records them (``subframe_*`` keys, :mod:`colgnn_core.sim.dataset`). A failure raises
:class:`SimulationError` naming the frame and leaves the state unchanged.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import ipctk
import numpy as np
import scipy.sparse as sp

from colgnn_core.errors import SimulationError
from colgnn_core.geometry.transforms import interpolate_poses, validate_pose
from colgnn_core.sim.elasticity import StableNeoHookean, lumped_mass
from colgnn_core.sim.linear_solve import NewtonSystemSolver

_DEBUG = bool(os.environ.get("COLGNN_SIM_DEBUG"))  # print every Newton iteration (developer aid)
_SETTLE_CACHE: dict = {}  # settled frame-0 object positions per (scene, mesh, tool pose, solver options)
DMIN_SCALE = 4.0  # the object-tool gap dmin kept by the solver, in units of dhat (module docstring)
MAX_SUBFRAME_DEPTH = 4  # a frame whose solve fails is halved at most 4 times: up to 16 sub-frames (as the Predictor)


def _barrier(s: np.ndarray, s_hat: float):
    """ipctk's clamped log barrier b(s) = −(s − ŝ)² ln(s/ŝ) on squared distances s < ŝ, with b′ and b″."""
    ln = np.log(s / s_hat)
    dsh = s - s_hat
    b = -dsh * dsh * ln
    b1 = -2.0 * dsh * ln - dsh * dsh / s
    b2 = -2.0 * ln - 4.0 * dsh / s + dsh * dsh / (s * s)
    return b, b1, b2


@dataclass
class _ContactSet:
    """An ipctk CollisionMesh over a subset of the full vertices, with its DOF map and gap dmin."""

    mesh: ipctk.CollisionMesh
    full_ids: np.ndarray  # [n_cm] full vertex id of each collision vertex
    dof: np.ndarray  # [3 n_cm] full DOF index of each collision DOF
    dmin: float

    @classmethod
    def build(cls, full_rest: np.ndarray, edges: np.ndarray, faces: np.ndarray, dmin: float) -> "_ContactSet":
        mesh = ipctk.CollisionMesh.build_from_full_mesh(
            np.asfortranarray(full_rest), np.asfortranarray(edges.astype(np.int32)),
            np.asfortranarray(faces.astype(np.int32))
        )
        ids = np.array([mesh.to_full_vertex_id(i) for i in range(mesh.num_vertices)], dtype=np.int64)
        return cls(mesh, ids, (3 * ids[:, None] + np.arange(3)).reshape(-1), float(dmin))

    def vertices(self, x: np.ndarray) -> np.ndarray:
        """Collision-mesh vertex positions from full positions x [N+M,3]."""
        return np.asfortranarray(x[self.full_ids])


@dataclass
class StepStats:
    """Solver statistics of one time step."""

    newton_iterations: int
    kappa: float  # final barrier stiffness
    min_distance: float  # m: object–tool surface distance after the step (see IPCSimulator.tool_distance)
    ms: float  # wall time of the step (ms)
    converged: bool
    forced_tool_steps: int = 0  # phase-2 iterations that still had to move the tool onto its target
    subframes: int = 1  # implicit steps the frame took (1, or more when a solve failed and was halved)
    # (object [N,3], tool [M,3]) of the intermediate states the frame's motion passes through when its straight
    # frame-to-frame motion is not collision-free (see IPCSimulator.step); empty when it is.
    path: tuple = ()


class IPCSimulator:
    """Implicit-Euler IPC simulation of one scene's deformable object and kinematic tool.

    Args:
        scene: a :class:`colgnn_core.scenes.Scene` (object TetMesh, Tool, material, dt, gravity,
            ground_height, dhat, friction, tool_rest_pose; optional ``pinned`` vertex ids).
        newton_tol: Newton stops when ‖p‖_∞ < newton_tol · bbox_diagonal · dt (IPC's default 1e-2).
        dhat_scale: multiplies ``scene.dhat`` (the barrier activation distance).
        dmin_scale: minimum gap kept between surfaces, as a multiple of dhat (see module docstring).
        max_newton: Newton iteration cap per step (all phases); exceeding it raises SimulationError.
        kappa_eps: κ doubles while the closest barrier distance keeps shrinking below
            kappa_eps · bbox_diagonal (``dhat_epsilon_scale`` of ``ipctk.update_barrier_stiffness``;
            IPC's 1e-9 lets gaps collapse to ~1e-9 m and the CCD-limited line search crawl).
        kappa_min_scale: ``min_barrier_stiffness_scale`` of ``ipctk.initial_barrier_stiffness``
            (IPC uses 1e11; 1e13 cut Newton iterations by ~20% on the ci scenes: stiffer contact,
            larger equilibrium gaps, fewer CCD-limited steps); κ lies in [κ_min, 100·κ_min].
        tool_penalty: k of the mass-weighted tool penalty (relative to the mean vertex mass).
        friction_eps_v: friction's static/dynamic transition speed ε_v (m/s).
        friction_iterations: lagged-friction solves per step (1 = bases and normal forces from
            the start of the step, IPC's default; each extra one re-lags from the last solution).
        settle: before frame 0, let the object settle under gravity on its support (ground or
            pinned vertices), so a sequence starts from static equilibrium instead of sagging.
        verify: run the per-step verification (intersections, exact CCD of the frame motion).
        initial_tool_pose: tool pose [7] at frame 0 (default ``scene.tool_rest_pose``).
        self_contact: include the object's self-contact barrier (without the dmin gap).
    """

    def __init__(
        self,
        scene,
        newton_tol: float = 1e-2,
        dhat_scale: float = 1.0,
        dmin_scale: float = DMIN_SCALE,
        max_newton: int = 200,
        kappa_eps: float = 1e-4,
        kappa_min_scale: float = 1e13,
        tool_penalty: float = 1e6,
        friction_eps_v: float = 1e-3,
        friction_iterations: int = 1,
        settle: bool = True,
        verify: bool = True,
        initial_tool_pose: np.ndarray | None = None,
        self_contact: bool = True,
    ) -> None:
        self.scene = scene
        self.newton_tol = float(newton_tol)
        self.max_newton = int(max_newton)
        self.kappa_eps = float(kappa_eps)
        self.kappa_min_scale = float(kappa_min_scale)
        self.tool_penalty = float(tool_penalty)
        self.verify = bool(verify)
        self.dt = float(scene.dt)
        self.h = self.dt  # the time step being solved: dt, or dt / 2^k for a frame solved as sub-frames
        self.gravity = np.asarray(scene.gravity, dtype=np.float64).reshape(3)
        self.mu = float(getattr(scene, "friction", 0.0) or 0.0)
        self.friction_eps_v = float(friction_eps_v)
        self.friction_iterations = max(1, int(friction_iterations))

        mesh = scene.object
        self.rest = np.asarray(mesh.vertices, dtype=np.float64)
        self.n_obj = len(self.rest)
        self.elastic = StableNeoHookean(mesh, scene.material)
        self.mass = lumped_mass(mesh, scene.material.density)
        self.tool = scene.tool
        self.n_tool = len(self.tool.vertices)
        self.n_all = self.n_obj + self.n_tool
        self.tool_mass = float(self.mass.mean())
        lo, hi = self.rest.min(axis=0), self.rest.max(axis=0)
        self.bbox_diagonal = float(np.linalg.norm(hi - lo))
        self.dhat = float(scene.dhat) * float(dhat_scale)
        if not self.dhat > 0:
            raise ValueError(f"dhat must be positive, got {self.dhat}")
        self.dmin = float(dmin_scale) * self.dhat

        # Collision meshes: object surface + tool surface; interior object vertices are excluded.
        tool_faces = np.asarray(self.tool.faces, dtype=np.int64) + self.n_obj
        tool_edges = np.asarray(self.tool.edges, dtype=np.int64) + self.n_obj
        full_rest = np.vstack([self.rest, self.tool.world_vertices(np.asarray(scene.tool_rest_pose, dtype=np.float64))])
        edges_all = np.vstack([np.asarray(mesh.edges), tool_edges])
        faces_all = np.vstack([np.asarray(mesh.faces), tool_faces])
        # `cm`: every pair except tool–tool, no gap: what verification checks.
        self.cm = _ContactSet.build(full_rest, edges_all, faces_all, 0.0)
        if not np.array_equal(self.cm.full_ids[-self.n_tool :], np.arange(self.n_obj, self.n_all)):
            raise RuntimeError("unexpected collision-mesh vertex order")
        self.cm.mesh.can_collide = ipctk.make_static_obstacle_filter(self.cm.mesh.num_vertices - self.n_tool)
        # Barrier sets: object–tool pairs keep the dmin gap; object self-contact (optional) has none,
        # because rest meshes may have non-adjacent surface elements closer than dmin (bunny ears).
        tool_set = _ContactSet.build(full_rest, edges_all, faces_all, self.dmin)
        patches = (tool_set.full_ids >= self.n_obj).astype(np.int32)
        tool_set.mesh.can_collide = ipctk.make_vertex_patches_filter(patches)
        self.contact_sets = [tool_set]
        if self_contact:
            self.contact_sets.append(_ContactSet.build(self.rest, np.asarray(mesh.edges), np.asarray(mesh.faces), 0.0))
        self.self_set = (self.contact_sets[1] if self_contact else
                         _ContactSet.build(self.rest, np.asarray(mesh.edges), np.asarray(mesh.faces), 0.0))
        self.surface = np.asarray(mesh.surface_vertices, dtype=np.int64)
        self.ground = None if scene.ground_height is None else float(scene.ground_height)
        self.broad_phase = ipctk.LBVH()
        self.ccd = ipctk.AdditiveCCD()
        # Verification: exact Tight-Inclusion CCD, iteration-capped (the dmin gap keeps it fast).
        self.verify_ccd = ipctk.TightInclusionCCD(tolerance=1e-6, max_iterations=1_000_000)
        # Object self-contact keeps no gap (rest meshes have close non-adjacent elements): a real touch is what fails.
        self.verify_touch_ccd = ipctk.TightInclusionCCD(tolerance=1e-6, max_iterations=1_000_000,
                                                        conservative_rescaling=1.0)
        self.barrier_fn = ipctk.ClampedLogBarrier()

        pinned = getattr(scene, "pinned", None)
        self.pinned = np.zeros(self.n_obj, dtype=bool)
        if pinned is not None and np.asarray(pinned).size > 0:
            pinned = np.asarray(pinned)
            if pinned.dtype == bool:
                self.pinned[: len(pinned)] = pinned
            else:
                self.pinned[pinned.astype(np.int64)] = True

        self.kappa = 0.0
        self._settle = bool(settle)
        self.initial_tool_pose = validate_pose(scene.tool_rest_pose if initial_tool_pose is None else initial_tool_pose)
        self.settle_steps = 0          # implicit steps the last settle took (0: no settle; set by reset)
        self.settle_converged = True   # False: the object was still moving after the settle's step cap
        self.reset()

    # ================================================================== state
    def reset(self) -> None:
        """Back to frame 0: object at rest (settled under gravity if enabled), tool at its initial pose."""
        self.frame = 0
        self.kappa = 0.0
        self.linear = NewtonSystemSolver()  # fresh per run: a sequence's result does not depend on the one before
        self.tool_pose = self.initial_tool_pose.copy()
        self.x = np.vstack([self.rest, self.tool.world_vertices(self.tool_pose)])
        self.v = np.zeros((self.n_obj, 3))
        if self.ground is not None:
            gap = float((self.rest[self.surface, 2] - self.ground).min())
            if gap <= 0:
                raise SimulationError(f"scene {self.scene.name!r}: object rest mesh touches or crosses the ground "
                                      f"(gap {gap:.3g} m)")
        if ipctk.has_intersections(self.cm.mesh, self.cm.vertices(self.x), broad_phase=self.broad_phase):
            raise SimulationError(f"scene {self.scene.name!r}: frame 0 intersects (the tool at its initial pose cuts "
                                  "the object)")
        if self.tool_distance() <= self.dmin:
            raise SimulationError(f"scene {self.scene.name!r}: at frame 0 surfaces are closer than dmin = "
                                  f"{self.dmin:.3g} m")
        self.settle_steps, self.settle_converged = 0, True
        if self._settle and np.any(self.gravity != 0) and (self.ground is not None or self.pinned.any()):
            self._settle_under_gravity()

    def state(self) -> dict[str, np.ndarray]:
        """What the next frame depends on, as arrays (for a checkpoint): positions of object and tool ``x``
        [N+M,3] (m), object velocities ``v`` [N,3] (m/s), the barrier stiffness, the tool pose [7], the frame, and
        whether the linear solver gave up on Jacobi CG. The linear solver's lagged factors are not kept: a restored
        run solves its systems to the same tolerance from a fresh factor, so it agrees with an uninterrupted one to
        solver tolerance, not bit for bit."""
        return {"x": self.x.copy(), "v": self.v.copy(), "kappa": np.float64(self.kappa),
                "tool_pose": self.tool_pose.copy(), "frame": np.int64(self.frame),
                "jacobi_failed": np.bool_(self.linear.jacobi_failed)}

    def restore(self, state: dict[str, np.ndarray]) -> None:
        """Continue from a :meth:`state` of the same scene and solver options (SimulationError if its shapes do
        not fit this mesh)."""
        x, v = np.asarray(state["x"], dtype=np.float64), np.asarray(state["v"], dtype=np.float64)
        if x.shape != (self.n_all, 3) or v.shape != (self.n_obj, 3) or not (np.all(np.isfinite(x))
                                                                            and np.all(np.isfinite(v))):
            raise SimulationError(f"a saved simulator state of shape x {x.shape}, v {v.shape} does not fit this "
                                  f"scene ({self.n_all} and {self.n_obj} vertices), or is not finite")
        self.x, self.v = x.copy(), v.copy()
        self.kappa = float(state["kappa"])
        self.tool_pose = validate_pose(np.asarray(state["tool_pose"], dtype=np.float64))
        self.frame = int(state["frame"])
        self.linear = NewtonSystemSolver()
        self.linear.jacobi_failed = bool(state["jacobi_failed"])

    @property
    def positions(self) -> np.ndarray:
        """Object vertex positions [N,3] (m), a copy."""
        return self.x[: self.n_obj].copy()

    @property
    def tool_positions(self) -> np.ndarray:
        """Tool surface vertex positions [M,3] (m), a copy."""
        return self.x[self.n_obj :].copy()

    # ============================================================ energy terms
    def _collisions(self, cs: "_ContactSet", x: np.ndarray):
        vc = cs.vertices(x)
        c = ipctk.NormalCollisions()
        c.build(cs.mesh, vc, self.dhat, dmin=cs.dmin, broad_phase=self.broad_phase)
        return c, vc

    def _to_full_csr(self, cs: "_ContactSet", h_cm) -> sp.csr_matrix:
        """Collision-mesh DOF matrix -> full DOF CSR [3(N+M)]²."""
        n = 3 * self.n_all
        hc = h_cm.tocoo()
        return sp.csr_matrix((hc.data, (cs.dof[hc.row], cs.dof[hc.col])), shape=(n, n))

    def _energy(self, x: np.ndarray, ctx: dict) -> float:
        """Incremental potential at full positions x [N+M,3]."""
        xo = x[: self.n_obj]
        dx = xo - ctx["x_tilde"]
        e = 0.5 * float(np.einsum("i,ij,ij->", self.mass, dx, dx))
        e += self.h**2 * self.elastic.energy(xo)
        for k, cs in enumerate(self.contact_sets):
            c, vc = self._collisions(cs, x)
            if len(c):
                e += self.kappa * ipctk.BarrierPotential(self.dhat, 1.0)(c, cs.mesh, vc)
            if ctx.get("friction") is not None and len(ctx["friction"][0][k]):
                tcs, fp, _, _ = ctx["friction"]
                e += fp(tcs[k], cs.mesh, np.asfortranarray(vc - cs.vertices(self.x)))
        bg = self._ground_barrier(xo, 0)[0]
        if not np.isfinite(bg):
            return np.inf
        e += self.kappa * bg
        if ctx.get("friction") is not None:
            e += self._ground_friction(xo, ctx["friction"][3], 0)[0]
        if ctx["phase"] == 1:
            d = x[self.n_obj :] - ctx["target"]
            e += 0.5 * self.tool_penalty * self.tool_mass * float(np.sum(d * d))
        return e

    def _contact_grad_hess(self, x: np.ndarray, ctx: dict | None, want_hess: bool, kappa: float):
        """κ·barrier (+ friction) gradient [3(N+M)] and PSD Hessian (CSR) over all DOFs."""
        n = 3 * self.n_all
        g = np.zeros(n)
        h = sp.csr_matrix((n, n)) if want_hess else None
        psd = ipctk.PSDProjectionMethod.CLAMP
        for k, cs in enumerate(self.contact_sets):
            c, vc = self._collisions(cs, x)
            if len(c):
                bp = ipctk.BarrierPotential(self.dhat, kappa)
                g[cs.dof] += bp.gradient(c, cs.mesh, vc)
                if want_hess:
                    h = h + self._to_full_csr(cs, bp.hessian(c, cs.mesh, vc, project_hessian_to_psd=psd))
            if ctx is not None and ctx.get("friction") is not None and len(ctx["friction"][0][k]):
                tcs, fp, _, _ = ctx["friction"]
                u = np.asfortranarray(vc - cs.vertices(self.x))
                g[cs.dof] += fp.gradient(tcs[k], cs.mesh, u)
                if want_hess:
                    h = h + self._to_full_csr(cs, fp.hessian(tcs[k], cs.mesh, u, project_hessian_to_psd=psd))
        xo = x[: self.n_obj]
        _, gg, hg = self._ground_barrier(xo, 2 if want_hess else 1)
        if gg is not None:
            g[3 * gg[0] + 2] += kappa * gg[1]
            if want_hess:
                h = h + sp.csr_matrix((kappa * hg, (3 * gg[0] + 2, 3 * gg[0] + 2)), shape=(n, n))
        if ctx is not None and ctx.get("friction") is not None:
            _, gf, hf = self._ground_friction(xo, ctx["friction"][3], 2 if want_hess else 1)
            if gf is not None:
                ids, gxy = gf
                dof = (3 * ids[:, None] + np.arange(2)).reshape(-1)
                g[dof] += gxy.reshape(-1)
                if want_hess:
                    rows = np.repeat(dof.reshape(-1, 2), 2, axis=1).reshape(-1)
                    cols = np.tile(dof.reshape(-1, 2), (1, 2)).reshape(-1)
                    h = h + sp.csr_matrix((hf.reshape(-1), (rows, cols)), shape=(n, n))
        return g, h

    # ---------------------------------------------------------------- ground
    def _ground_barrier(self, xo: np.ndarray, order: int):
        """Unscaled ground barrier Σ b(d²) over object surface vertices with d < dhat.

        Returns (value, (ids, ∂/∂z) or None, ∂²/∂z² or None); value is inf at or below the ground.
        """
        if self.ground is None:
            return 0.0, None, None
        d = xo[self.surface, 2] - self.ground
        act = d < self.dhat
        if not act.any():
            return 0.0, None, None
        if np.any(d[act] <= 0):
            return np.inf, None, None
        b, b1, b2 = _barrier(d[act] ** 2, self.dhat**2)
        if order == 0:
            return float(b.sum()), None, None
        dz = d[act]
        grad = (self.surface[act], b1 * 2.0 * dz)
        hess = np.maximum(b2 * 4.0 * dz * dz + 2.0 * b1, 0.0) if order > 1 else None  # PSD: clamp the 1-D term
        return float(b.sum()), grad, hess

    def _ground_lambda(self, xo: np.ndarray) -> np.ndarray | None:
        """Lagged normal force magnitudes [N] of the ground barrier (κ·|∂b/∂d|; 0 off contact)."""
        if self.ground is None:
            return None
        _, g, _ = self._ground_barrier(xo, 1)
        lam = np.zeros(self.n_obj)
        if g is not None:
            lam[g[0]] = self.kappa * np.abs(g[1])
        return lam

    def _ground_friction(self, xo: np.ndarray, lam: np.ndarray | None, order: int):
        """IPC's smoothed lagged Coulomb friction against the ground, μ·λ_i·f0(‖u_i‖), u = tangential step."""
        if lam is None or self.mu <= 0:
            return 0.0, None, None
        ids = np.flatnonzero(lam > 0)
        if not ids.size:
            return 0.0, None, None
        eps = self.friction_eps_v * self.h
        u = xo[ids, :2] - self.x[ids, :2]  # self.x is the state at the start of the step
        y = np.linalg.norm(u, axis=1)
        w = self.mu * lam[ids]
        slow = y < eps
        f0 = np.where(slow, -(y**3) / (3 * eps * eps) + y * y / eps + eps / 3.0, y)
        if order == 0:
            return float(w @ f0), None, None
        # f1(y)/y: the friction force is −μλ f1(y) û = −μλ (f1/y) u; smooth at y = 0.
        f1_over_y = np.where(slow, -y / (eps * eps) + 2.0 / eps, 1.0 / np.maximum(y, 1e-300))
        grad = (ids, (w * f1_over_y)[:, None] * u)
        hess = None
        if order > 1:
            # Eigenvalues: f1/y across u, f1'(y) along u (≥ 0 for y ≤ eps, 0 beyond): already PSD.
            f1p = np.where(slow, 2.0 / eps - 2.0 * y / (eps * eps), 0.0)
            uh = u / np.maximum(y, 1e-300)[:, None]
            uu = uh[:, :, None] * uh[:, None, :]
            hess = w[:, None, None] * (f1_over_y[:, None, None] * (np.eye(2) - uu) + f1p[:, None, None] * uu)
        return float(w @ f0), grad, hess

    def _friction_context(self, x: np.ndarray):
        """Lagged friction (tangent bases, normal forces) from state x; None when μ = 0."""
        if self.mu <= 0:
            return None
        tcs = []
        for cs in self.contact_sets:
            c, vc = self._collisions(cs, x)
            tc = ipctk.TangentialCollisions()
            if len(c):
                tc.build(cs.mesh, vc, c, ipctk.BarrierPotential(self.dhat, self.kappa), self.mu)
            tcs.append(tc)
        fp = ipctk.FrictionPotential(self.friction_eps_v * self.h)
        return tcs, fp, None, self._ground_lambda(x[: self.n_obj])

    def _barrier_distance_sq(self, x: np.ndarray) -> float:
        """Squared smallest barrier distance (pair distance − dmin; ground distance) among active pairs; inf if
        none."""
        d2 = np.inf
        for cs in self.contact_sets:
            c, vc = self._collisions(cs, x)
            if len(c):
                d2 = min(d2, float((np.sqrt(c.compute_minimum_distance(cs.mesh, vc)) - cs.dmin) ** 2))
        if self.ground is not None:
            dz = x[self.surface, 2] - self.ground
            dz = dz[dz < self.dhat]
            if dz.size:
                d2 = min(d2, float((dz * dz).min()))
        return d2

    # ============================================================== line search
    def _inversion_step_bound(self, x: np.ndarray, p: np.ndarray, alpha: float) -> float:
        """Largest α' ≤ alpha keeping det(Ds) ≥ 0.1·det(Ds₀) for every tet along x + α p.

        det(A + αB) = c0 + c1 α + c2 α² + c3 α³. Tets whose higher-order terms cannot reach
        0.9·c0 on [0, alpha] are skipped; the rest are sampled at 64 points.
        """
        el = self.elastic
        a = el.edge_matrix(x[: self.n_obj])
        b = el.edge_matrix(p[: self.n_obj])
        c0 = np.linalg.det(a)
        c1 = np.einsum("kij,kij->k", el.cofactor(a), b)
        c2 = np.einsum("kij,kij->k", el.cofactor(b), a)
        c3 = np.linalg.det(b)
        bound = (np.abs(c1) + (np.abs(c2) + np.abs(c3) * alpha) * alpha) * alpha
        risky = bound >= 0.9 * c0
        if not risky.any():
            return alpha
        s = np.linspace(0.0, alpha, 65)[1:]
        c0r, c1r, c2r, c3r = c0[risky, None], c1[risky, None], c2[risky, None], c3[risky, None]
        bad = c0r + s * (c1r + s * (c2r + s * c3r)) < 0.1 * c0r
        if not bad.any():
            return alpha
        k = int(np.where(bad.any(axis=1), bad.argmax(axis=1), len(s)).min())
        return float(s[k - 1]) if k > 0 else float(s[0]) / 64.0

    def _max_step(self, x: np.ndarray, p: np.ndarray) -> float:
        """Largest α ≤ 1 that is collision-free (CCD, keeping dmin) and inversion-free."""
        alpha = 1.0
        for cs in self.contact_sets:
            a = ipctk.compute_collision_free_stepsize(
                cs.mesh, cs.vertices(x), cs.vertices(x + p), min_distance=cs.dmin, broad_phase=self.broad_phase,
                narrow_phase_ccd=self.ccd
            )
            alpha = min(alpha, float(a))
        if self.ground is not None:
            # Ground CCD: keep every surface vertex above 10% of its current gap (z is linear in α).
            d0 = x[self.surface, 2] - self.ground
            dz = p[self.surface, 2]
            hit = d0 + dz < 0.1 * d0
            if hit.any():
                alpha = min(alpha, float(np.min(0.9 * d0[hit] / -dz[hit])))
        if alpha > 0:
            alpha = self._inversion_step_bound(x, p, alpha)
        return alpha

    # ================================================================== Newton
    def _solve(self, h: sp.csr_matrix, rhs: np.ndarray, free: np.ndarray) -> np.ndarray:
        """Solve H p = rhs on the free DOFs (p = 0 elsewhere): CG or sparse Cholesky (``sim.linear_solve``)."""
        idx = np.flatnonzero(free)
        if len(idx) == h.shape[0]:
            hf = h
        elif idx[-1] == len(idx) - 1:  # a leading block (tool fixed, nothing pinned): slice, no gather
            hf = h[: len(idx), : len(idx)]
        else:
            hf = h[idx][:, idx]
        p = np.zeros_like(rhs)
        # The free set differs only in the tool's DOFs (free in phase 1): its size names it.
        p[idx] = self.linear.solve(hf, np.ascontiguousarray(rhs[idx]), len(idx))
        return p

    def _free_mask(self, tool_free: bool) -> np.ndarray:
        free = np.ones((self.n_all, 3))
        free[: self.n_obj][self.pinned] = 0.0
        if not tool_free:
            free[self.n_obj :] = 0.0
        return free.reshape(-1)

    def _newton(self, x: np.ndarray, ctx: dict, stats: dict) -> tuple[np.ndarray, bool]:
        """Projected Newton until ‖p‖_∞ < tol; returns (x, converged).

        Phase 1: tool DOFs free under the penalty. Phase 2: tool DOFs fixed; while they are not on
        ``ctx['target']`` their remaining displacement is a prescribed step, CCD-clamped together
        with the object's response and taken without the energy test (a forced boundary motion need
        not lower the energy); what CCD cuts off is carried to the next iteration.
        """
        n = 3 * self.n_all
        phase = ctx["phase"]
        free = self._free_mask(phase == 1)
        tol = self.newton_tol * self.bbox_diagonal * self.h
        h2 = self.h**2
        mass_dof = np.zeros(n)
        mass_dof[: 3 * self.n_obj] = np.repeat(self.mass, 3)
        if phase == 1:
            mass_dof[3 * self.n_obj :] = self.tool_penalty * self.tool_mass
        diag = sp.diags(mass_dof, format="csr")
        prev_d2 = self._barrier_distance_sq(x)
        e0 = self._energy(x, ctx)
        while stats["iters"] < self.max_newton:
            stats["iters"] += 1
            xo = x[: self.n_obj]
            g = np.zeros(n)
            g[: 3 * self.n_obj] = ((self.mass[:, None] * (xo - ctx["x_tilde"])).reshape(-1)
                                   + h2 * self.elastic.gradient(xo).reshape(-1))
            if phase == 1:
                g[3 * self.n_obj :] = (self.tool_penalty * self.tool_mass
                                       * (x[self.n_obj :] - ctx["target"])).reshape(-1)
            gc, hc = self._contact_grad_hess(x, ctx, True, self.kappa)
            g += gc
            he = self.elastic.hessian(xo)
            # Pad the 3N×3N elastic CSR to all DOFs (tool rows empty) without copying its indices.
            indptr = np.concatenate([he.indptr, np.full(3 * self.n_tool, he.indptr[-1])])
            hmat = sp.csr_matrix((he.data * h2, he.indices, indptr), shape=(n, n)) + diag + hc
            forced = np.zeros((self.n_all, 3))
            if phase == 2:
                forced[self.n_obj :] = ctx["target"] - x[self.n_obj :]
            is_forced = bool(np.any(forced != 0))
            rhs = -g - hmat @ forced.reshape(-1) if is_forced else -g
            p = self._solve(hmat, rhs * free, free).reshape(-1, 3) + forced
            if not is_forced and np.abs(p).max() < tol:
                return x, True
            alpha = self._max_step(x, p)
            if is_forced:
                if alpha <= 1e-8:
                    raise SimulationError(f"frame {self.frame + 1}: the tool cannot move on to its target (CCD step "
                                          f"{alpha:.2g})")
                stats["forced"] += 1
                x = x + alpha * p
                if alpha >= 1.0:
                    x[self.n_obj :] = ctx["target"]  # exactly, not up to round-off
                e0 = self._energy(x, ctx)
            else:
                if alpha <= 0:
                    raise SimulationError(f"frame {self.frame + 1}: the CCD line search returned a zero step")
                while True:
                    xn = x + alpha * p
                    en = self._energy(xn, ctx)
                    if en <= e0:
                        break
                    alpha *= 0.5
                    if alpha < 1e-10:
                        # No decrease along a descent direction: stalled at round-off level.
                        return x, np.abs(p).max() < 10 * tol
                x, e0 = xn, en
            stats["trace"].append(x.copy())  # every state the solver moves through (see step)
            d2 = self._barrier_distance_sq(x)
            if _DEBUG:
                dev = np.abs(x[self.n_obj :] - ctx["target"]).max()
                print(f"  it{stats['iters']} ph{phase} forced={is_forced} alpha={alpha:.3g} |p|={np.abs(p).max():.3g} "
                      f"d={np.sqrt(d2):.3g} kappa={self.kappa:.3g} tooldev={dev:.3g}")
            if np.isfinite(d2) and np.isfinite(prev_d2):
                kappa = ipctk.update_barrier_stiffness(
                    prev_d2, d2, stats["kappa_max"], self.kappa, self.bbox_diagonal, dhat_epsilon_scale=self.kappa_eps
                )
                if kappa != self.kappa:
                    self.kappa = kappa
                    e0 = self._energy(x, ctx)
            prev_d2 = d2
        return x, False

    def _init_kappa(self, x: np.ndarray, x_tilde: np.ndarray) -> tuple[float, float]:
        """IPC's initial κ (balancing the barrier against inertia + elasticity) and κ_max."""
        xo = x[: self.n_obj]
        free = self._free_mask(False)
        ge = np.zeros(3 * self.n_all)
        ge[: 3 * self.n_obj] = ((self.mass[:, None] * (xo - x_tilde)).reshape(-1)
                                + self.h**2 * self.elastic.gradient(xo).reshape(-1))
        gb, _ = self._contact_grad_hess(x, None, False, 1.0)
        kappa, kappa_max = ipctk.initial_barrier_stiffness(
            self.bbox_diagonal,
            self.barrier_fn,
            self.dhat,
            float(self.mass.mean()),
            ge * free,
            gb * free,
            min_barrier_stiffness_scale=self.kappa_min_scale,
            dmin=self.dmin,
        )
        return float(kappa), float(kappa_max)

    def _solve_step(self, target: np.ndarray, x_tilde: np.ndarray) -> tuple[np.ndarray, dict]:
        """Minimise the incremental potential with the tool driven to ``target`` [M,3]."""
        x = self.x.copy()
        kappa, kappa_max = self._init_kappa(x, x_tilde)
        # κ persists across steps (never below this step's IPC initial value): contact that needed a
        # stiffer barrier in the last frame needs it in this one too.
        self.kappa = min(max(kappa, self.kappa), kappa_max)
        stats = {"iters": 0, "kappa_max": kappa_max, "forced": 0, "trace": []}
        ctx = {"x_tilde": x_tilde, "phase": 1, "target": target, "friction": self._friction_context(x)}
        if not np.array_equal(x[self.n_obj :], target):
            x, ok = self._newton(x, ctx, stats)
            if not ok:
                return x, {**stats, "converged": False}
        ctx["phase"] = 2
        # The tool is within force/(k·m̄) of its target: snap it there if that tool-only move is
        # collision-free (a CCD query, no factorisation); otherwise phase 2 forces it there.
        rest = np.zeros_like(x)
        rest[self.n_obj :] = target - x[self.n_obj :]
        snapped = np.any(rest != 0) and self._max_step(x, rest) >= 1.0
        if snapped:
            x[self.n_obj :] = target
            stats["trace"].append(x.copy())
        if stats["iters"] > 0 and (not np.any(rest != 0) or (
                snapped and np.abs(rest).max() < self.newton_tol * self.bbox_diagonal * self.h)):
            # Phase 1 converged and the snap moved the tool by less than the Newton tolerance: the
            # object's Newton step it induces, H_oo⁻¹ H_ot δ, is of the same size, so x is converged.
            ok = True
        else:
            x, ok = self._newton(x, ctx, stats)
        for _ in range(self.friction_iterations - 1):
            if not ok or self.mu <= 0:
                break
            # Lagging update: friction bases/forces from the converged contact state.
            ctx["friction"] = self._friction_context(x)
            x, ok = self._newton(x, ctx, stats)
        return x, {**stats, "converged": ok}

    def step(self, tool_pose_next: np.ndarray) -> StepStats:
        """Advance one frame (dt) with the tool moved to ``tool_pose_next`` [7]; verify the frame.

        Solving: one implicit step; if Newton fails or the new state does not verify, the frame is solved again as
        two sub-frames of dt/2 (the tool at the slerp midpoint), recursively, down to ``2**MAX_SUBFRAME_DEPTH``.
        Motion (see :meth:`motion_free`): the straight frame-to-frame motion must be collision-free. Where it is
        not (a surface swinging round the cone's sharp tip within a frame: measured on a 2.5 ms sub-frame of the
        ci cone_bunny press-and-drag, both ends 1.6 mm from the tip and the chord 0.7 µm from it), the frame's
        motion is the piecewise-linear path through as few of the solver's own intermediate states (line-search
        iterates, sub-frame ends) as make every piece collision-free; consecutive ones are one CCD-checked solver
        move apart. They are returned in ``StepStats.path``.

        Raises SimulationError naming the frame when the finest split fails; the simulator state then stays at the
        previous frame.
        """
        t0 = time.perf_counter()
        pose = validate_pose(tool_pose_next)
        start = (self.x, self.v, self.kappa, self.tool_pose)
        frame = self.frame + 1
        stats = {"iters": 0, "forced": 0, "subframes": 0, "trace": [self.x]}
        try:
            self._advance(self.tool_pose, pose, self.dt, 0, frame, stats)
            path = self._motion_path(stats["trace"], frame) if self.verify else []
        except BaseException:
            self.x, self.v, self.kappa, self.tool_pose = start
            raise
        finally:
            self.h = self.dt
        self.frame = frame
        return StepStats(
            newton_iterations=int(stats["iters"]),
            kappa=float(self.kappa),
            min_distance=self.tool_distance(),
            ms=(time.perf_counter() - t0) * 1e3,
            converged=True,
            forced_tool_steps=int(stats["forced"]),
            subframes=int(stats["subframes"]),
            path=tuple((x[: self.n_obj].copy(), x[self.n_obj :].copy()) for x in path),
        )

    def _advance(self, pose_a: np.ndarray, pose_b: np.ndarray, h: float, depth: int, frame: int,
                 stats: dict) -> None:
        """Move the state from the tool at ``pose_a`` to ``pose_b`` in time ``h``: one implicit step, else two
        halves (recursively, ``depth`` halvings so far). The solver's states go to ``stats['trace']``."""
        try:
            self._substep(pose_b, h, frame, stats)
            return
        except SimulationError as exc:
            if depth >= MAX_SUBFRAME_DEPTH:
                raise SimulationError(f"{exc} (solved as {2 ** depth} sub-frames)") from None
        mid = interpolate_poses(pose_a, pose_b, np.array([0.5]))[0]
        self._advance(pose_a, mid, 0.5 * h, depth + 1, frame, stats)
        self._advance(mid, pose_b, 0.5 * h, depth + 1, frame, stats)

    def _substep(self, pose: np.ndarray, h: float, frame: int, stats: dict) -> None:
        """One implicit Euler step of length ``h`` with the tool driven to ``pose``; the new state verified
        (:meth:`_verify_state`) and taken. SimulationError, state unchanged, when Newton or the verification fails."""
        target = self.tool.world_vertices(pose)
        xo = self.x[: self.n_obj]
        self.h = h
        x_tilde = xo + h * self.v + h**2 * self.gravity
        x_tilde[self.pinned] = xo[self.pinned]
        kappa_before = self.kappa
        try:
            x_new, st = self._solve_step(target, x_tilde)
            stats["iters"] += st["iters"]
            stats["forced"] += st["forced"]
            if not st["converged"]:
                raise SimulationError(f"frame {frame}: Newton did not converge in {self.max_newton} iterations")
            if self.verify:
                self._verify_state(x_new, target, frame)
        except BaseException:
            self.kappa = kappa_before
            raise
        stats["trace"].extend(st["trace"])
        if not np.array_equal(stats["trace"][-1], x_new):
            stats["trace"].append(x_new)
        stats["subframes"] += 1
        self.v = (x_new[: self.n_obj] - xo) / h
        self.x = x_new
        self.tool_pose = pose

    def motion_free(self, x0: np.ndarray, x1: np.ndarray) -> bool:
        """Is the straight motion x0 -> x1 (all vertices [N+M,3], linear) collision-free? Object–tool pairs by
        Tight-Inclusion CCD with its default line-search clearance (the Predictor's guarantee, checked by
        ``colgnn_core.collision.exact.tool_step_free``); object self-contact by a real touch."""
        ts = self.contact_sets[0]
        if not ipctk.is_step_collision_free(ts.mesh, ts.vertices(x0), ts.vertices(x1), broad_phase=self.broad_phase,
                                            narrow_phase_ccd=self.verify_ccd):
            return False
        ss = self.self_set
        return bool(ipctk.is_step_collision_free(ss.mesh, ss.vertices(x0), ss.vertices(x1),
                                                 broad_phase=self.broad_phase, narrow_phase_ccd=self.verify_touch_ccd))

    def _motion_path(self, trace: list, frame: int) -> list:
        """Intermediate states of ``trace`` (the solver's states from the last frame to the new one) whose
        piecewise-linear path is collision-free (:meth:`motion_free`); none when the straight motion is. From each
        state the next is the trace's last, else the one halfway there, and so on."""
        path, i, last = [], 0, len(trace) - 1
        while i < last:
            j = last
            while j > i + 1 and not self.motion_free(trace[i], trace[j]):
                j = i + (j - i) // 2
            if j == i + 1 and not self.motion_free(trace[i], trace[j]):
                raise SimulationError(f"frame {frame}: the motion from frame {frame - 1} is not collision-free, not "
                                      "even along the solver's own steps")
            if j < last:
                path.append(trace[j])
            i = j
        return path

    def tool_distance(self) -> float:
        """Smallest object–tool surface distance (m): exact mesh pairs within dmin + 2·dhat, else the
        analytic tool SDF at the object's surface vertices (the ideal shape the mesh is inscribed in)."""
        cs = self.contact_sets[0]
        vc = cs.vertices(self.x)
        c = ipctk.NormalCollisions()
        c.build(cs.mesh, vc, self.dmin + 2.0 * self.dhat, broad_phase=self.broad_phase)
        if len(c):
            return float(np.sqrt(c.compute_minimum_distance(cs.mesh, vc)))
        return float(self.tool.sdf(self.x[self.surface], self.tool_pose).min())

    def min_distance(self, include_ground: bool = True) -> float:
        """Smallest distance (m) over object–tool, object self-contact (within 2·dhat) and object–ground."""
        d = self.tool_distance()
        if len(self.contact_sets) > 1:
            cs = self.contact_sets[1]
            vc = cs.vertices(self.x)
            c = ipctk.NormalCollisions()
            c.build(cs.mesh, vc, 2.0 * self.dhat, broad_phase=self.broad_phase)
            if len(c):
                d = min(d, float(np.sqrt(c.compute_minimum_distance(cs.mesh, vc))))
        if include_ground and self.ground is not None:
            d = min(d, float((self.x[self.surface, 2] - self.ground).min()))
        return d

    def _verify_state(self, x1: np.ndarray, target: np.ndarray, frame: int) -> None:
        """A new state: no intersection (object–tool or self), above the ground, no inverted tet, the tool exactly on
        ``target``. (The motion into it is checked by :meth:`step`.)"""
        if ipctk.has_intersections(self.cm.mesh, self.cm.vertices(x1), broad_phase=self.broad_phase):
            raise SimulationError(f"frame {frame}: the surface intersects itself or the tool")
        if self.ground is not None and np.any(x1[self.surface, 2] <= self.ground):
            raise SimulationError(f"frame {frame}: an object vertex is at or below the ground")
        j = self.elastic.jacobians(x1[: self.n_obj])
        if np.any(j <= 0):
            raise SimulationError(f"frame {frame}: {int(np.sum(j <= 0))} tets inverted")
        if not np.array_equal(x1[self.n_obj :], target):
            raise SimulationError(f"frame {frame}: the tool is off its target by "
                                  f"{np.abs(x1[self.n_obj:] - target).max():.3g} m")

    # ================================================================= settle
    def _settle_under_gravity(self, max_steps: int = 100) -> None:
        """Static equilibrium under gravity on the ground / pinned vertices; the result is cached.

        A free object first drops rigidly to 0.5·dhat above the ground (the scene places it a few
        dhat up so frame 0 is contact-free; falling that gap under the barrier's CCD takes many
        tiny steps). Then implicit steps of dt with the velocity zeroed, until a step moves less
        than the Newton tolerance.
        """
        key = (
            getattr(self.scene, "name", ""),
            getattr(self.scene, "resolution", ""),
            self.rest.tobytes(),
            self.x[self.n_obj :].tobytes(),
            self.dhat,
            self.dmin,
            self.newton_tol,
            self.mu,
            self.kappa_eps,
            self.elastic.j_hat,
        )
        hit = _SETTLE_CACHE.get(key)
        if hit is not None:
            # kappa is state too: a cached settle must start frame 1 exactly like a computed one
            self.x[: self.n_obj], self.kappa, self.settle_steps, self.settle_converged = hit
            self.v = np.zeros((self.n_obj, 3))
            self.linear = NewtonSystemSolver()
            return
        if self.ground is not None and not self.pinned.any():
            drop = float((self.x[self.surface, 2] - self.ground).min()) - 0.5 * self.dhat
            if drop > 0:
                self.x[: self.n_obj, 2] -= drop
        tol = self.newton_tol * self.bbox_diagonal * self.dt
        target = self.x[self.n_obj :].copy()
        self.settle_steps, self.settle_converged = 0, False
        for _ in range(max_steps):
            self.settle_steps += 1
            xo = self.x[: self.n_obj]
            x_tilde = xo + self.dt**2 * self.gravity
            x_tilde[self.pinned] = xo[self.pinned]
            x_new, st = self._solve_step(target, x_tilde)
            if not st["converged"]:
                raise SimulationError(f"scene {self.scene.name!r}: settling under gravity did not converge")
            moved = float(np.abs(x_new[: self.n_obj] - xo).max())
            self.x = x_new
            if moved < tol:
                self.settle_converged = True
                break
        self.v = np.zeros((self.n_obj, 3))
        # The linear solver's state (lagged factors, Jacobi given up) is state too: frame 1 starts from a fresh one
        # whether the settle was computed or cached, or the same seed would give a different sequence to 1e-9 m.
        self.linear = NewtonSystemSolver()
        if len(_SETTLE_CACHE) > 16:
            _SETTLE_CACHE.clear()
        _SETTLE_CACHE[key] = (self.x[: self.n_obj].copy(), self.kappa, self.settle_steps, self.settle_converged)
