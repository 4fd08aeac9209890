"""Meshes with known answers for the morph tests."""

import numpy as np


def sphere(r=1.0, n=40):
    th, ph = np.meshgrid(np.linspace(0, np.pi, n), np.linspace(0, 2 * np.pi, 2 * n, endpoint=False), indexing="ij")
    v = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1).reshape(-1, 3) * r
    f = []
    m = 2 * n
    for i in range(n - 1):
        for j in range(m):
            a, b, c, d = i * m + j, i * m + (j + 1) % m, (i + 1) * m + j, (i + 1) * m + (j + 1) % m
            f += [[a, c, b], [b, c, d]]
    return v, np.array(f)


def box(n=8):
    """Closed unit cube [-1, 1]³, each side an n×n grid, outward winding, shared corner/edge vertices."""
    g = np.linspace(-1, 1, n + 1)
    vs, fs, off = [], [], 0
    for axis in range(3):
        for sign in (-1.0, 1.0):
            a, b = [k for k in range(3) if k != axis]
            uu, vv = np.meshgrid(g, g, indexing="ij")
            p = np.zeros(((n + 1) ** 2, 3))
            p[:, axis], p[:, a], p[:, b] = sign, uu.ravel(), vv.ravel()
            q = []
            for i in range(n):
                for j in range(n):
                    c0, c1, c2, c3 = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
                    q += [[c0, c1, c2], [c0, c2, c3]]
            q = np.array(q)
            # outward: (e_a × e_b) points along +axis for (a, b) in cyclic order
            if np.cross(np.eye(3)[a], np.eye(3)[b])[axis] * sign < 0:
                q = q[:, ::-1]
            vs.append(p)
            fs.append(q + off)
            off += len(p)
    v = np.concatenate(vs)
    f = np.concatenate(fs)
    uniq, inv = np.unique(np.round(v, 9), axis=0, return_inverse=True)
    return uniq, inv.ravel()[f]


def outward_sphere(n=40):
    v, f = sphere(1.0, n)
    from foundation.mesh import face_normals
    from foundation.mesh_metrics import triangle_areas

    # the grid repeats each pole vertex: weld the copies (else the poles are open borders), drop the triangles
    # that become degenerate
    _, first, inverse = np.unique(np.round(v, 9), axis=0, return_index=True, return_inverse=True)
    f = first[inverse.ravel()][f]
    f = f[(triangle_areas(v, f) > 1e-12) & (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])]
    if np.mean(np.sum(face_normals(v, f) * v[f].mean(axis=1), axis=1)) < 0:
        f = f[:, ::-1].copy()
    return v, f
