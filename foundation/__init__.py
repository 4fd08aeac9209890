"""photoreal's foundation: the bottom layer every stage uses (imports only ``mi_plugins`` of the project).

========================  =============================================================
module                    what
========================  =============================================================
``errors``                the error classes (each names a file or parameter; CLI exit codes)
``files``                 atomic writes, output-path checks, JSON results, digests
``imageio``               EXR (multi-layer) and PNG I/O, sRGB transfer, figures
``mesh``                  mesh I/O (OBJ with UVs, PLY with colours, any via pymeshlab), basic ops
``mesh_metrics``          Chamfer, normal consistency, spikes, inverted triangles
``metrics``               image metrics (PSNR, SSIM, ꟻLIP, MSE, …)
``features``              pretrained ImageNet MobileNetV2 (hash-checked): features, FID/KID, perceptual distance
``assets``                the vendored assets (HDRIs, scans, meshes) and envmap dicts
``scene``                 loading/rendering Mitsuba scenes with clear errors; intrinsic layers
``progress``              progress bars
``threads``               Dr.Jit / torch thread counts (determinism)
``checkpoint``            checkpoint files (npz + JSON tree, no pickle)
``optim_state``           save/restore Dr.Jit and torch optimiser state (exact resume)
``loop``                  the one resumable training loop (budgets, NaN policy, metrics JSON)
``pool``                  many independent items on a spawn process pool or a Ray cluster (same results)
``records``               typed dataclasses ↔ JSON with the bad field named
``bridge``                every ``dr.wrap`` crossing between torch and Dr.Jit
``validate``              checks of settings values (finite, ranges) that name the parameter
========================  =============================================================
"""
