"""The chips' elastic energy: linear bricks with incompatible modes, a stiffness matrix
assembled once per press.

Every chip of the contact model is a structured block of rectangular bricks
(:func:`meshing.contact_model.chip_block`). A trilinear brick locks in bending; with
Wilson and Taylor's nine incompatible modes (the element CalculiX calls C3D8I), condensed
out per element, a rectangular brick carries pure bending exactly, so two bricks through
a chip's thickness bend it as plate theory says. The strain is small (linear
elasticity): a chip pressed into the voids under it rotates by a few degrees at most, and
the contact between chips is where the problem is nonlinear.

Voigt order: xx, yy, zz, yz, xz, xy, with engineering shear strains.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

__all__ = [
    "HEX_CORNERS",
    "brick_stiffness",
    "assemble",
    "rotate_stiffness",
    "node_volumes",
    "brick_volumes",
    "hex_boundary_triangles",
]

# Natural coordinates of a brick's corners in C3D8 (and VTK_HEXAHEDRON) order.
HEX_CORNERS = np.array(
    [
        [-1, -1, -1],
        [1, -1, -1],
        [1, 1, -1],
        [-1, 1, -1],
        [-1, -1, 1],
        [1, -1, 1],
        [1, 1, 1],
        [-1, 1, 1],
    ],
    dtype=float,
)
_GAUSS = HEX_CORNERS / np.sqrt(3.0)  # 2 x 2 x 2 points, weight 1 each


def _strain_rows(gradients: np.ndarray) -> np.ndarray:
    """(..., 6, 3k) strain-displacement rows of k nodal gradients (..., k, 3)."""
    *lead, k, _ = gradients.shape
    b = np.zeros((*lead, 6, 3 * k))
    gx, gy, gz = gradients[..., 0], gradients[..., 1], gradients[..., 2]
    b[..., 0, 0::3] = gx
    b[..., 1, 1::3] = gy
    b[..., 2, 2::3] = gz
    b[..., 3, 1::3] = gz
    b[..., 3, 2::3] = gy
    b[..., 4, 0::3] = gz
    b[..., 4, 2::3] = gx
    b[..., 5, 0::3] = gy
    b[..., 5, 1::3] = gx
    return b


def brick_stiffness(corners: np.ndarray, stiffness: np.ndarray) -> np.ndarray:
    """(m, 24, 24) stiffness matrices (N/mm) of m bricks with incompatible modes.

    corners: (m, 8, 3) mm, C3D8 order. stiffness: (m, 6, 6) MPa, each brick's elasticity
    in the world frame (Voigt). The nine incompatible modes are condensed statically;
    their gradients use the Jacobian at the brick's centre (Taylor's correction, so the
    element passes the patch test when distorted).
    """
    corners = np.asarray(corners, dtype=float)
    m = len(corners)
    kuu = np.zeros((m, 24, 24))
    kua = np.zeros((m, 24, 9))
    kaa = np.zeros((m, 9, 9))
    # The Jacobian at the centre, for the modes' gradients.
    centre_dn = HEX_CORNERS / 8.0  # dN/dxi at xi = 0
    j0 = np.einsum("ai,maj->mij", centre_dn, corners)
    det0 = np.linalg.det(j0)
    inv0 = np.linalg.inv(j0)
    for xi in _GAUSS:
        terms = 1.0 + HEX_CORNERS * xi  # (8, 3)
        dn = np.empty((8, 3))
        dn[:, 0] = HEX_CORNERS[:, 0] * terms[:, 1] * terms[:, 2] / 8
        dn[:, 1] = HEX_CORNERS[:, 1] * terms[:, 0] * terms[:, 2] / 8
        dn[:, 2] = HEX_CORNERS[:, 2] * terms[:, 0] * terms[:, 1] / 8
        jac = np.einsum("ai,maj->mij", dn, corners)  # d x_j / d xi_i
        det = np.linalg.det(jac)
        if np.any(det <= 0):
            raise ValueError("brick_stiffness: a brick is inverted or flat")
        inv = np.linalg.inv(jac)
        grad = np.einsum("mij,aj->mai", inv, dn)  # dN_a/dx_i
        b = _strain_rows(grad)
        # Modes 1 - xi_k^2: d/dxi_k = -2 xi_k, mapped with the centre's Jacobian.
        dmode = np.diag(-2.0 * xi)  # (mode, natural direction)
        mode_grad = np.einsum("mij,kj->mki", inv0, dmode) * (det0 / det)[:, None, None]
        g = _strain_rows(mode_grad)
        cb = np.einsum("mij,mjk->mik", stiffness, b)
        cg = np.einsum("mij,mjk->mik", stiffness, g)
        kuu += np.einsum("mji,mjk->mik", b, cb) * det[:, None, None]
        kua += np.einsum("mji,mjk->mik", b, cg) * det[:, None, None]
        kaa += np.einsum("mji,mjk->mik", g, cg) * det[:, None, None]
    return kuu - np.einsum("mij,mjk->mik", kua, np.linalg.solve(kaa, np.transpose(kua, (0, 2, 1))))


def assemble(cells: np.ndarray, element_matrices: np.ndarray, n_nodes: int) -> sp.csr_matrix:
    """The global (3n, 3n) matrix of element matrices over ``cells`` (m, k) node ids."""
    dofs = (3 * cells[:, :, None] + np.arange(3)).reshape(len(cells), -1)
    rows = np.repeat(dofs, dofs.shape[1], axis=1).ravel()
    cols = np.tile(dofs, (1, dofs.shape[1])).ravel()
    matrix = sp.coo_matrix(
        (element_matrices.ravel(), (rows, cols)), shape=(3 * n_nodes, 3 * n_nodes)
    ).tocsr()
    return (matrix + matrix.T) * 0.5  # exactly symmetric


def _voigt_pairs():
    return [(0, 0), (1, 1), (2, 2), (1, 2), (0, 2), (0, 1)]


def rotate_stiffness(local: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """(n, 6, 6) world-frame Voigt stiffness of the ``local`` (6, 6) one, for n frames.

    frames: (n, 3, 3), rows the material axes 1, 2, 3 in the world frame.
    """
    pairs = _voigt_pairs()
    tensor = np.zeros((3, 3, 3, 3))
    for a, (i, j) in enumerate(pairs):
        for b, (k, m) in enumerate(pairs):
            for p, q in {(i, j), (j, i)}:
                for r, s in {(k, m), (m, k)}:
                    tensor[p, q, r, s] = local[a, b]
    world = np.einsum("nai,nbj,nck,ndl,abcd->nijkl", frames, frames, frames, frames, tensor)
    out = np.empty((len(frames), 6, 6))
    for a, (i, j) in enumerate(pairs):
        for b, (k, m) in enumerate(pairs):
            out[:, a, b] = world[:, i, j, k, m]
    return out


def brick_volumes(corners: np.ndarray) -> np.ndarray:
    """(m,) mm^3, the volumes of m trilinear bricks (2 x 2 x 2 Gauss points)."""
    total = np.zeros(len(corners))
    for xi in _GAUSS:
        terms = 1.0 + HEX_CORNERS * xi
        dn = np.empty((8, 3))
        dn[:, 0] = HEX_CORNERS[:, 0] * terms[:, 1] * terms[:, 2] / 8
        dn[:, 1] = HEX_CORNERS[:, 1] * terms[:, 0] * terms[:, 2] / 8
        dn[:, 2] = HEX_CORNERS[:, 2] * terms[:, 0] * terms[:, 1] / 8
        total += np.linalg.det(np.einsum("ai,maj->mij", dn, corners))
    return total


def node_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(n,) mm^3, each node's share of the volume of the bricks around it (lumped)."""
    share = np.repeat(brick_volumes(points[cells]) / cells.shape[1], cells.shape[1])
    return np.bincount(cells.ravel(), weights=share, minlength=len(points))


# A brick's faces (C3D8 node order, outward), each as two triangles.
_FACES = ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7))


def hex_boundary_triangles(cells: np.ndarray) -> np.ndarray:
    """(t, 3) the outward triangles of the faces that only one brick of ``cells`` has."""
    quads = np.concatenate([cells[:, list(face)] for face in _FACES])
    keys = np.sort(quads, axis=1)
    _, first, counts = np.unique(keys, axis=0, return_index=True, return_counts=True)
    outer = quads[np.sort(first[counts == 1])]
    return np.concatenate([outer[:, [0, 1, 2]], outer[:, [0, 2, 3]]])
