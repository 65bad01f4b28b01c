"""The Taichi kernels of tisem: one module per step of the method, plus the map's layout.

Every step of `tisem.mapper.Mapper.integrate` (steps 2-8 run by
`tisem.scan_integrator.ScanIntegrator`), where its kernels live:

| step of the method                        | module       | kernels / functions             |
|-------------------------------------------|--------------|---------------------------------|
| 1. preprocess: sensor -> map frame, range | rasterize.py | locate_kernel (locate, to_local)|
|    and height band, the live window       |              |                                 |
| 2. downsample / voxelize: points sorted   | rasterize.py | locate_kernel, scatter_kernel   |
|    by leaf block, then by voxel; centroid | table.py     | column_slots                    |
|    and class histogram per voxel          | training.py  | sort_blocks, training_kernel    |
| 3. redundant-voxel filter                 | training.py  | voxel_kept                      |
| 4. semantic uncertainty (entropy)         | entropy.py   | normalized_entropy, fresh_length|
| 5. kernel length                          | entropy.py   | assign_lengths, length_of       |
|                                           |              | (adaptive: computed in the      |
|                                           |              | update's pass, at the pending   |
|                                           |              | mark of layout.py)              |
| 6. sparse kernel k(v, p)                  | bki.py       | sparse_kernel_of_r2             |
| 7. Bayesian kernel update                 | bki.py       | update_kernel (gather form)     |
|    csm: the voxel's own histogram         | fusion.py    | fuse_histograms                 |
| 8. temporal fusion (lazy decay)           | fusion.py    | fuse_voxel, decay_factor        |
| 9. query                                  | query.py     | query, lookup                   |
|    class centroids: where in its voxel    | training.py  | training_kernel (per row)       |
|    each of the two leading classes lies   | centroids.py | merge_row (length pass),        |
|                                           |              | nearer_class                    |
| free space (optional): dynamic points,    | raycast.py   | flag_dynamic, mark_hits,        |
|    hits, rays that clear what they cross  |              | cast_free, traverse (3-D DDA)   |
|    the memory of space seen empty         | seen_empty.py| forget_expired_blocks, ...      |
| the live window (eviction, reload)        | window.py    | find_leaving_blocks, ...        |
| the SNode tree and the scan's table       | layout.py    | MapFields, table limits         |
| a scan's constants, the kernels' settings | params.py    | ScanParams, KernelSettings      |

Kernels that depend on a mode are built by cached factories (`*_kernel(...)`), which close over
their compile-time settings and branch with `ti.static`; a scan's constants travel as one
`ScanParams` argument pack.
"""
