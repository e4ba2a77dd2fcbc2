"""The rest compliance K^-1 that the contact prior asks for: exact, or compressed so that a fine mesh answers in
real time.

Each active-set round the contact prior (``sim.contact_prior``) needs two things of K^-1 for the U free vertices
that its k constraints touch (M [3U,k]: each constraint's weighted normals on its vertices' coordinates):

* the dual matrix S = M^T C_UU M [k,k], C_UU = K^-1 restricted to those vertices' coordinates;
* the response u = C_{:,U} w [3N_free] to the forces w = M lambda [3U].

``ExactCompliance`` reads both from the cached columns K^-1 E_v (``sim.rest_stiffness``). Why a second kind: on the
full banana (5,062 free vertices) a roller that slides reaches new vertices every step, and their back-substitutions
cost 64% of a 60-1,000 ms step; yet the full mesh's prior scores 0.12 where the ``ci`` one scores 0.30 (validation
seed 11, prior alone; docs/FIDELITY.md, sessions 43-44).

``ModalCompliance``:

* **The dual from K^-1 ~ Phi Lambda^-1 Phi^T + N.** Phi [3N_free,m], Lambda [m]: the m lowest modes of K, the body's
  bend and shift. N: sparse, the exact K^-1 minus the modal part for each pair of surface vertices whose rest
  positions lie within ``radius``: the dent under a tool is local and needs the high modes. S = B Lambda^-1 B^T +
  M^T N_UU M with B = M^T Phi_U [k,m]: O(k^2 m), about 1 ms for 163 rows at 150 modes.
* **The response exactly**, by one back-substitution (2.5 ms on the full banana). The modes' response scored 0.167
  against 0.127 on validation seed 11: a point force's far field is not smooth in K's lowest modes, while the
  multipliers that the dual gives are. Or, where even that is too slow (``read``: 16 ms on the full torus),
  from the modes and the near field at the graph's nodes only, in about 2 ms: with the near field the torus's edge
  prior scores as the exact one does (docs/FIDELITY.md, session 49).
* **Set-up**: a shift-invert Lanczos for the modes and one back-substitution per surface coordinate for the near
  field (17 s on the full banana), kept on disk (:func:`cache_dir`), keyed by K's fingerprint and the settings.

With the contact prior's vertex constraints, the full banana's prior costs 6.2 ms a step in contact (median, one
thread), against 60-1,000 ms exact and about 1 ms on the ``ci`` mesh.

Units: m, N.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from numba import njit
from scipy import sparse
from scipy.sparse.linalg import LinearOperator, eigsh
from scipy.spatial import cKDTree
from tqdm import tqdm

from colgnn_core.io import atomic_write
from colgnn_core.jit_cache import user_cache
from colgnn_core.sim.rest_stiffness import RestStiffness

__all__ = ["BATCH_VERTICES", "MODES", "NEAR_FIELD_EDGES", "ExactCompliance", "ModalCompliance", "cache_dir",
           "coordinates", "hash_ids"]

BATCH_VERTICES = 200  # surface vertices whose exact columns are solved together while building the near field
MODES = 150           # the full banana's validation seeds 2 / 5 / 8 / 11 and held-out seed 5, prior alone: 150 modes
                      # 0.213 / 0.419 / 0.717 / 0.130, 0.494; 300 modes 0.214 / 0.429 / 0.713 / 0.127, 0.496; exact
                      # 0.204 / - / - / 0.122 (docs/FIDELITY.md, session 44)
NEAR_FIELD_EDGES = 4  # the near field's reach in mean surface edges (the full banana: 10 mm; 15 mm scored the same)


def coordinates(stiffness: RestStiffness, vertices: np.ndarray) -> np.ndarray:
    """[3V]: the free coordinates (rows of K) of free mesh vertices ``vertices`` [V], x y z each."""
    return (3 * stiffness.free_index[np.asarray(vertices, dtype=np.int64)][:, None] + np.arange(3)).reshape(-1)


def cache_dir() -> Path:
    """``$XDG_CACHE_HOME/colgnn/compliance`` (default ``~/.cache/colgnn/compliance``)."""
    return user_cache("compliance")


class ExactCompliance:
    """K^-1 from the cached unit-force responses of ``stiffness`` (exact; a vertex's first contact costs three
    back-substitutions)."""

    def __init__(self, stiffness: RestStiffness):
        self.stiffness = stiffness

    def dual(self, vertices: np.ndarray, m: np.ndarray | sparse.spmatrix) -> np.ndarray:
        """[k,k]: M^T C_UU M for free mesh vertices ``vertices`` [U] and M ``m`` [3U,k]."""
        own = coordinates(self.stiffness, vertices)
        c_own = np.concatenate([c[:, own] for c in self.stiffness.columns(vertices.tolist())], axis=0)  # [3U,3U]
        cm = np.asarray(c_own @ m)
        return np.asarray(m.T @ cm)

    def response(self, vertices: np.ndarray, w: np.ndarray) -> np.ndarray:
        """[3N_free] (m): the free displacement for forces ``w`` [3U] (N) on ``vertices`` [U]."""
        free_u = np.zeros(3 * self.stiffness.n_free)
        for c, wu in zip(self.stiffness.columns(vertices.tolist()), w.reshape(-1, 3)):
            free_u += wu @ c
        return free_u


class ModalCompliance:
    """K^-1 ~ Phi Lambda^-1 Phi^T + N (module docstring) for ``stiffness``.

    surface: [S] mesh ids of the vertices the tool can touch (glued ones are dropped); modes: m; radius: the near
    field's reach (m); cache: folder for the set-up (None: no disk cache); read: None answers :meth:`response`
    exactly, by a back-substitution; mesh ids [R] answer it from the modes and the near field at those vertices
    only (the surface, where the near field lives, should be among them; elsewhere the response reads 0)."""

    def __init__(self, stiffness: RestStiffness, surface: np.ndarray, modes: int, radius: float,
                 cache: Path | None = None, read: np.ndarray | None = None):
        self.stiffness = stiffness
        surface = np.asarray(surface, dtype=np.int64)
        surface = np.unique(surface[stiffness.free_index[surface] >= 0])
        self.modes, self.radius = int(modes), float(radius)
        path = None
        if cache is not None:
            key = f"{stiffness.fingerprint}-{hash_ids(surface)}-m{self.modes}-r{self.radius:.6g}"
            path = Path(cache) / f"{key}.npz"
        if path is not None and path.is_file():
            with np.load(path) as z:
                self.inv_lam, self.phi = z["inv_lam"], z["phi"]
                self.near = sparse.csr_matrix((z["near_data"], z["near_indices"], z["near_indptr"]),
                                              shape=(3 * stiffness.n_free,) * 2)
        else:
            self.inv_lam, self.phi = self._lowest_modes()
            self.near = self._near_field(surface)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                with atomic_write(path) as fh:
                    np.savez(fh, inv_lam=self.inv_lam, phi=self.phi, near_data=self.near.data,
                             near_indices=self.near.indices, near_indptr=self.near.indptr)
        blocks = self.near.tobsr(blocksize=(3, 3))            # N's 3x3 vertex blocks, by free vertex row
        self._read_rows, self._phi_read, self._near_columns = None, None, None
        if read is not None:
            read = np.asarray(read, dtype=np.int64)
            self._read_rows = coordinates(stiffness, np.unique(read[stiffness.free_index[read] >= 0]))
            # float32: the product is memory-bound (full torus, 15,252 rows x 150 modes: 4.3 ms in float64, 1.4 ms)
            self._phi_read = np.ascontiguousarray(self.phi[self._read_rows], dtype=np.float32)
            self._near_columns = self.near.T   # N is symmetric: its transpose is N by columns, without a copy
        self._block_ptr, self._block_col, self._block = blocks.indptr, blocks.indices, blocks.data
        # Load the compiled kernel now, not at the first contact: there it cost a step 100-200 ms (a bench's p95)
        self.dual(surface[:1], sparse.csc_matrix(np.ones((3, 1))))

    @classmethod
    def for_surface(cls, stiffness: RestStiffness, faces: np.ndarray, cache: Path | None = None,
                    read: np.ndarray | None = None) -> "ModalCompliance":
        """MODES modes and a near field of NEAR_FIELD_EDGES mean edges of the surface ``faces`` [F,3] at the rest;
        ``read``: as the constructor's."""
        faces = np.asarray(faces, dtype=np.int64)
        tri = stiffness.rest[faces]
        edge = float(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).mean())
        return cls(stiffness, np.unique(faces), MODES, NEAR_FIELD_EDGES * edge, cache=cache, read=read)

    def _lowest_modes(self) -> tuple[np.ndarray, np.ndarray]:
        """(1/Lambda [m] (m/N), Phi [3N_free,m]): K's m lowest eigenpairs by shift-invert Lanczos about 0."""
        n = self.stiffness.hessian.shape[0]
        k = min(self.modes, n - 2)
        op = LinearOperator((n, n), matvec=lambda x: self.stiffness.solve(np.asarray(x, dtype=np.float64)),
                            dtype=np.float64)
        vals, vecs = eigsh(self.stiffness.hessian, k=k, sigma=0.0, which="LM", OPinv=op)
        return 1.0 / vals, np.ascontiguousarray(vecs)

    def _near_field(self, surface: np.ndarray) -> sparse.csr_matrix:
        """N [3N_free,3N_free] (symmetric): exact minus modal K^-1 for surface pairs within ``radius``."""
        st = self.stiffness
        rest = st.rest[surface]
        pairs = cKDTree(rest).query_ball_point(rest, self.radius)
        rows, cols, data = [], [], []
        for start in tqdm(range(0, surface.size, BATCH_VERTICES), desc="near-field compliance", unit="batch",
                          leave=False):
            batch = np.arange(start, min(start + BATCH_VERTICES, surface.size))
            own = coordinates(st, surface[batch])
            rhs = np.zeros((3 * st.n_free, own.size))
            rhs[own, np.arange(own.size)] = 1.0
            exact = st.solve(rhs)                                                     # [3N_free,3B]
            for j, i in enumerate(batch):
                r = coordinates(st, surface[pairs[i]])                                # [3q] near rows
                c = own[3 * j:3 * j + 3]
                block = exact[r, 3 * j:3 * j + 3] - (self.phi[r] * self.inv_lam) @ self.phi[c].T   # [3q,3]
                rows.append(np.repeat(r, 3))
                cols.append(np.tile(c, r.size))
                data.append(block.reshape(-1))
        n = 3 * st.n_free
        near = sparse.csr_matrix((np.concatenate(data), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
        return ((near + near.T) * 0.5).tocsr()   # the exact columns are symmetric to the solver's precision

    def dual(self, vertices: np.ndarray, m: np.ndarray | sparse.spmatrix) -> np.ndarray:
        """[k,k]: M^T C_UU M for free mesh vertices ``vertices`` [U] and M ``m`` [3U,k]."""
        own = coordinates(self.stiffness, vertices)
        b = np.asarray(m.T @ self.phi[own])                                           # [k,m]
        rows = sparse.csr_matrix(m)
        fi = self.stiffness.free_index[np.asarray(vertices, dtype=np.int64)]
        slot = np.full(self.stiffness.n_free, -1, dtype=np.int64)
        slot[fi] = np.arange(fi.size)
        s = (b * self.inv_lam) @ b.T
        # M^T N_UU M from N's 3x3 vertex blocks, never forming N_UU: 0.1 ms for the banana's 163 contact vertices,
        # where slicing N twice and multiplying took 2 ms
        _add_near(s, fi, slot, self._block_ptr, self._block_col, self._block, rows.indptr, rows.indices, rows.data)
        return s

    def near_block(self, vertices: np.ndarray) -> np.ndarray:
        """[3U,3U]: N between free mesh vertices ``vertices`` [U] (dense; for checks)."""
        own = coordinates(self.stiffness, vertices)
        return self.near[own][:, own].toarray()

    def response(self, vertices: np.ndarray, w: np.ndarray) -> np.ndarray:
        """[3N_free] (m): the free displacement for forces ``w`` [3U] (N) on ``vertices`` [U].

        Without ``read``: exact, one back-substitution (2.5 ms on the full banana, 16 ms on the full torus). The
        modes' response alone (1.4 ms at 300 modes) scored 0.167 where the exact one scores 0.127 on the banana's
        validation seed 11: a point force's far field is not smooth in K's modes.
        With ``read``: Phi_R Lambda^-1 Phi_U^T w + N_{:,U} w at the ``read`` vertices (0 elsewhere). The near field
        gives the dent that the modes miss: the edge prior alone on the full torus scored 0.281 / 0.337 on validation
        and 0.436 / 0.410 / 0.624 / 0.669 held out, where the exact response scores 0.269 / 0.315 and 0.448 / 0.390 /
        0.628 / 0.675 (docs/FIDELITY.md, session 49), in about 2 ms instead of 16."""
        if self._read_rows is not None:
            own = coordinates(self.stiffness, vertices)
            coef = (self.inv_lam * (w @ self.phi[own])).astype(np.float32)                 # [m]
            free_u = np.asarray(self._near_columns[:, own] @ w).reshape(-1)                # the surface's near field
            free_u[self._read_rows] += self._phi_read @ coef
            return free_u
        rhs = np.zeros(3 * self.stiffness.n_free)
        rhs[coordinates(self.stiffness, vertices)] = w
        return self.stiffness.solve(rhs)


@njit(cache=True)
def _add_near(s: np.ndarray, fi: np.ndarray, slot: np.ndarray, block_ptr: np.ndarray, block_col: np.ndarray,
              block: np.ndarray, m_ptr: np.ndarray, m_col: np.ndarray, m_val: np.ndarray) -> None:
    """s [k,k] += M^T N_UU M: for each block N_ab (a, b among the U vertices, ``slot`` their place), every pair of
    M's entries on a's and b's coordinates (M as CSR rows ``m_ptr``, ``m_col``, ``m_val``; row 3a+i)."""
    for a in range(fi.size):
        for p in range(block_ptr[fi[a]], block_ptr[fi[a] + 1]):
            b = slot[block_col[p]]
            if b < 0:
                continue
            for i in range(3):
                for e in range(m_ptr[3 * a + i], m_ptr[3 * a + i + 1]):
                    k1, v1 = m_col[e], m_val[e]
                    for j in range(3):
                        c = v1 * block[p, i, j]
                        for f in range(m_ptr[3 * b + j], m_ptr[3 * b + j + 1]):
                            s[k1, m_col[f]] += c * m_val[f]


def hash_ids(ids: np.ndarray) -> str:
    """8 hex digits naming an id array (the surface a near field was built for)."""
    return hashlib.sha256(np.ascontiguousarray(ids, dtype=np.int64).tobytes()).hexdigest()[:8]
