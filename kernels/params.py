"""What the kernels of a scan read: its constants as one struct argument, and the compile-time
settings each kernel is built for.

Per map the mapper keeps one `ScanParams` value (a Taichi argument pack, so a kernel takes one
argument instead of two dozen scalars) and refreshes its per-scan members before every scan. An
argument pack rather than a struct: its members compile to the very loads separate arguments
do, so the kernels' fast-math code, and with it the map, stays bitwise the same (a struct
argument's members are loaded where they are used, which changes how sums are associated). Like
a field, a ScanParams value belongs to the runtime it was made in (taichi 1.7.4 supports
argument packs on the CPU and CUDA backends). The choices
that pick code paths are not arguments at all: the kernel factories (`functools.cache`) close
over a `KernelSettings` and branch with `ti.static`, so every mode compiles to kernels without
the branches of the other modes.
"""

import weakref
from dataclasses import dataclass

import taichi as ti
from taichi.lang import impl
from taichi.lang.argpack import ArgPack

vec3i = ti.types.vector(3, ti.i32)
vec3f = ti.types.vector(3, ti.f32)

ScanParams = ti.types.argpack(
    # the sensor pose in the map's local frame (local metres: world minus the map origin)
    rotation=ti.types.matrix(3, 3, ti.f32),  # R_local_sensor
    translation_m=vec3f,  # the sensor's position, local metres
    center_vox=vec3i,  # the sensor's voxel: the centre of the live window and the scan table
    limit_vox=vec3i,  # a kept point's voxel lies within this of center_vox on every axis
    min_range2_m2=ti.f32,  # the range band, squared (points outside it are dropped)
    max_range2_m2=ti.f32,
    min_z_m=ti.f32,  # the height band, sensor frame
    max_z_m=ti.f32,
    resolution_m=ti.f32,
    inv_resolution=ti.f32,  # 1 / resolution_m, rounded once on the host
    time_rel_s=ti.f32,  # the scan's time, seconds since the map's first scan
    stamp=ti.i32,  # the scan's number from 1 on (marks of the coarse `near` table)
    min_points=ti.i32,  # the redundant-voxel filter: fewer points and a voxel is dropped
    reach_blk=ti.i32,  # the longest kernel, in leaf blocks
    fixed_length_m=ti.f32,  # the kernel length of every voxel (fixed-length modes; csm: any > 0)
    length_min_m=ti.f32,  # the adaptive length's range: L = min + (max - min) * entropy
    length_max_m=ti.f32,
    prior=ti.f32,  # pseudo-count of every class in the entropy's p(c|v)
    sigma0=ti.f32,  # the sparse kernel's scale
    kernel_cutoff=ti.f32,  # the update's pairs lie within this fraction of the kernel length
    inv_tau=ti.f32,  # 1 / tau of the decay (0 for tau = inf: plain accumulation)
)

# every ScanParams value made by new_scan_params, with the runtime it belongs to
_made: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def new_scan_params(**members) -> ArgPack:
    """A ScanParams value of the running runtime (use this, never ScanParams(...) directly).

    taichi 1.7.4 frees an argument pack when Python collects it by asking the *running* runtime
    to delete the pack's C++ address. A pack of an earlier runtime (whose memory went with that
    runtime) that is collected late, by the cycle collector or after a reassignment, can
    therefore free a pack of the running runtime that the allocator placed at the same address,
    and the next kernel that reads it crashes the process at random. So before a new pack is
    made, every pack of an earlier runtime forgets its address, and its finalizer deletes
    nothing.
    """
    runtime = impl.get_runtime()
    for pack, made_in in list(_made.items()):
        if made_in() is not runtime:
            pack._ArgPack__argpack = None  # the finalizer's delete_argpack(None) is a no-op
            del _made[pack]
    pack = ScanParams(**members)
    _made[pack] = weakref.ref(runtime)
    return pack


# KernelSettings.kernel_length
NO_KERNEL = "none"  # csm: a voxel's own histogram is its update
FIXED_LENGTH = "fixed"  # bki: one length for every voxel
ADAPTIVE_LENGTH = "adaptive"  # the length from the entropy of the voxel's class distribution
# KernelSettings.decay
EXPONENTIAL = "exponential"  # alpha = exp(-dt / tau); tau = inf (1 / tau = 0) gives alpha = 1
FORGET = "forget"  # tau = 0: every update replaces the voxel's history (alpha = 0)
PER_CLASS = "per_class"  # alpha_c = exp(-dt / tau_c): movable classes fade faster


@dataclass(frozen=True)
class KernelSettings:
    """The compile-time choices of a map's kernels (hashable: the factories' cache key)."""

    kernel_length: str = ADAPTIVE_LENGTH
    decay: str = EXPONENTIAL
    unit_weight: bool = False  # a training voxel weighs once, not by its point count
    # some classes' evidence reaches less far than the receiver's length: the update reads a
    # per-class table (kernels/bki.py); off, the update never reads it
    evidence_caps: bool = False
    per_voxel: bool = False  # the update's parallel loop: per voxel (GPUs), per block (CPUs)
    # adaptive length: a voxel whose evidence for one of these classes (ids) is at least
    # long_kernel_share of its leading class's takes the longest kernel (kernels/entropy.py);
    # () compiles no test
    long_kernel_classes: tuple[int, ...] = ()
    long_kernel_share: float = 1.0
    # ... and whose z layer holds at least this many live voxels within 2 of it (0: no test)
    long_kernel_min_neighbours: int = 0

    def __post_init__(self):
        if self.kernel_length not in (NO_KERNEL, FIXED_LENGTH, ADAPTIVE_LENGTH):
            raise ValueError(f"unknown kernel_length {self.kernel_length!r}")
        if self.decay not in (EXPONENTIAL, FORGET, PER_CLASS):
            raise ValueError(f"unknown decay {self.decay!r}")

    @property
    def adaptive(self) -> bool:
        return self.kernel_length == ADAPTIVE_LENGTH

    @property
    def uses_kernel(self) -> bool:
        return self.kernel_length != NO_KERNEL
