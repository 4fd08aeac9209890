"""Cut ``face000_border_curl.npz`` out of a stored morph result (see make_face000_border_curl.md).

Usage: python make_face000_border_curl.py WORK_DIR OUT.npz  (WORK_DIR: `bench morph`'s morph_work)."""
import glob
import sys

import numpy as np

from foundation.mesh import face_normals, read_ply
from foundation.mesh_metrics import truth_surface
from inverse.morph.mesh_edit import border_zone

work, out = sys.argv[1], sys.argv[2]
v_start, f, _ = read_ply(glob.glob(f"{work}/bench_face000/start_remesh*.ply")[0])
v, _, _ = read_ply(f"{work}/suite_face000/morphed.ply")
turned = border_zone(f, len(v)) & (np.sum(face_normals(v, f) * face_normals(v_start, f), axis=1) < 0.5)
near = np.zeros(len(v), bool)
near[f[turned].ravel()] = True
for _ in range(4):  # four rings around the curled triangles
    near[f[near[f].any(axis=1)].ravel()] = True
keep = near[f].all(axis=1)
used = np.unique(f[keep])
index = np.full(len(v), -1)
index[used] = np.arange(len(used))
gv, gf, _ = read_ply(f"{work}/bench_face000/ground_truth.ply")
truth = truth_surface(gv, gf)
# the truth's normal nearest each kept triangle's centroid in the result (the suite's facing test, per triangle)
n_truth = truth.normals[truth.tree.query(v[f[keep]].mean(axis=1))[1]]
np.savez_compressed(out, v=v[used].astype(np.float32), v_start=v_start[used].astype(np.float32),
                    f=index[f[keep]].astype(np.int32), n_truth=n_truth.astype(np.float32))
print(f"{out}: {len(used)} vertices, {keep.sum()} faces, {turned.sum()} turned border triangles in the result")
