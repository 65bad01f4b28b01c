"""Configuration: a dataclass per concern, loaded from YAML, overridable with `key=value`.

Every field has one rule (`MAPPER_RULES`, `RUN_RULES`, tisem/config_rules.py): its type, its
range, and that it is finite. `MapperConfig.validate()` applies them, then the rules between
fields, then asks the map geometry (`tisem.geometry.MapGeometry`) whether a map of these sizes
can be built. A mistake is one `ConfigError` line naming the key, the value and what is allowed.

YAML is read with safe tags only and with YAML 1.2 numbers: `1e-4` is the number a user means,
not the string YAML 1.1 makes of it; a quoted `"0.2"` stays a string, and is refused as one.
Every results folder gets the resolved config (`config.yaml`), so a run can be repeated.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np
import yaml

from tisem.config_rules import (
    INPUTS,
    MAX_CLASSES,
    MODES,
    QUERY_BLENDS,
    THIN_CLASSES,
    VEHICLE_CLASSES,
    Choice,
    ClassNames,
    Flag,
    Folder,
    Number,
    check_fields,
    read_yaml,
    unknown_name,
    yaml_value,
)
from tisem.errors import ConfigError

__all__ = [
    "MODES",
    "INPUTS",
    "MAX_CLASSES",
    "MapperConfig",
    "RunConfig",
    "ConfigError",
    "load_config",
    "save_config",
    "to_dict",
    "set_value",
    "mapper_config_from_dict",
    "run_config_from_dict",
]


@dataclass
class MapperConfig:
    """The method's parameters (docs/method.md). Lengths in metres unless the name says voxels."""

    mode: str = "st"  # st | adaptive | spatial | bki | csm
    resolution_m: float = 0.2  # voxel edge
    num_classes: int = 20
    # 1. preprocess: points outside [min_range, max_range] or the height band are dropped
    min_range_m: float = 2.0  # the ego vehicle's own returns
    max_range_m: float = 80.0
    # the height band, relative to the sensor: it crops only what is physically implausible
    # (a road going downhill lies metres below the sensor, and a point dropped here is unmapped
    # and scores as wrong); the live window's z half-size must hold it plus the kernel reach
    min_z_m: float = -20.0
    max_z_m: float = 20.0
    # 3. redundant voxel filtering
    min_points: int = 1
    # 4.-6. entropy, adaptive length, sparse kernel (defaults measured: README "Parameters")
    prior: float = 2.0  # pseudo-count added to every class before the entropy is
    # taken: entropy then falls only as evidence piles up, so
    # sparse, young or contradicted voxels get long kernels
    sigma0: float = 1.0
    ell_min_m: float = 0.4
    ell_max_m: float = 1.2
    ell_fixed_vox: float = 4.0  # bki: fixed kernel length, in voxels
    # the update takes a point into a voxel's sum only within this fraction of the voxel's
    # kernel length: beyond 0.85 L the kernel is below 6.3e-4 of its peak and holds under
    # 6e-4 of its mass, while the shell from 0.85 L to L is 39 % of the sphere's volume, and
    # of the pairs the update tests (docs/method.md); 1 is the exact kernel
    kernel_cutoff: float = 0.85
    point_weight: str = "count"  # count: a training voxel weighs by its points; unit: once
    # evidence of these classes reaches at most ell_min_m from its training point, whatever the
    # receiving voxel's length: the network mistakes foliage for trunk and trunk for pole far
    # more often than the reverse, and a long kernel spreads each such label over a metre
    # (docs/method.md); [] gives every class the receiver's length
    thin_classes: list[str] = field(default_factory=lambda: list(THIN_CLASSES))
    # evidence of these classes reaches at most vehicle_cap_m: a car's points are dense near
    # the sensor, and the long kernels of the uncertain road and sidewalk voxels around and
    # beneath it carried its evidence over them. Won on both held-out real directions and both
    # calibrated streets (car IoU +2.0 to +6.0 pp); truck and other-vehicle are in none of those
    # data, so they are not in the default (docs/method.md). [] caps no vehicle
    vehicle_classes: list[str] = field(default_factory=lambda: list(VEHICLE_CLASSES))
    vehicle_cap_m: float = 0.6
    # adaptive modes: a voxel whose evidence for one of these classes is at least
    # long_kernel_share of its leading class's takes the longest kernel (ell_max_m), so that
    # the evidence around it decides: a patch of fence the network calls pole is outvoted by
    # the fence around it (thin_classes still keep that pole evidence from reaching far). [] by
    # default: it won on a fence-lined synthetic street and cost pole IoU on the real frames
    # (docs/method.md)
    long_kernel_classes: list[str] = field(default_factory=list)
    long_kernel_share: float = 0.25
    # ... and only where the voxel's z layer holds at least this many live voxels within 2 of it
    # (of 24): such a patch on a fence is as wide as the fence, while a pole is narrow and keeps
    # its short kernel (docs/method.md). 0: no such test
    long_kernel_min_neighbours: int = 0
    # 9. query: a point in the live window whose voxel holds no evidence takes the
    # kernel-weighted posterior of the live voxels within query_radius_m (missing), or 0 (off)
    query_blend: str = "missing"
    query_radius_m: float = 0.4
    # sub-voxel class boundaries: each voxel keeps where the points of its two leading classes
    # lie (their centroids); a query point in a voxel whose second class holds at least
    # centroid_ratio of the leading class's evidence takes the class whose centroid is nearer.
    # A 0.2 m voxel straddling a curb or a car's edge answers each side with its own class
    # (docs/method.md); off, a voxel answers its argmax everywhere
    class_centroids: bool = True
    centroid_ratio: float = 0.5
    # 8. temporal fusion
    tau_s: float = 5.0  # decay time constant (st mode)
    tau_movable_s: float | None = None  # tau of the movable classes (car ... motorcycle,
    # tisem.labels.MOVABLE_CLASSES) in st mode; None: tau_s
    # free space and moving objects (docs/dynamic.md): rays from the sensor to the hits make
    # the voxels they cross lose occupancy evidence; off, the map is exactly the map without it
    free_space: bool = False
    free_margin_m: float = 0.5  # a ray stops this far before its hit, or
    free_margin_fraction: float = 0.15  # this part of its range, whichever is more
    free_ray_stride: int = 3  # one ray per this many hit voxels (rays cost per voxel)
    empty_evidence: float = 1.0  # a voxel seen through this much more than hit is empty
    occupancy_cap: float = 3.0  # occupancy evidence is clamped to +-this
    # space a ray saw empty where the map holds no voxel is remembered this long: whatever
    # lands there meanwhile is dynamic (0: no such memory)
    seen_empty_s: float = 4.0
    # a live voxel next to space no ray has seen (neither in the map nor in that memory) keeps
    # its evidence when rays cross it: it holds a surface seen from one side (a car's roof),
    # which rays that pass it graze (needs seen_empty_s > 0)
    spare_beside_unseen: bool = True
    # a point of a class that cannot move (not tisem.labels.MOVABLE_CLASSES), in space seen
    # empty next to a live voxel its class leads, is not flagged dynamic: a pole or a trunk
    # sampled sparsely, beside which rays passed before a scan hit it there (needs
    # seen_empty_s > 0)
    spare_static_beside_own: bool = True
    # a live voxel led by a thin class that cannot move (thin_classes, not movable: pole,
    # traffic-sign, trunk) keeps its evidence when rays cross it: rays graze thin structure
    # sampled sparsely, in scans that hit nothing around the voxel
    spare_thin_static: bool = True
    # ... except one whose hits came and went within this many seconds and that no scan has
    # hit for longer than that (None: for ever): a pole or a trunk is hit now and then while
    # in view, a voxel a walker made with the network's trunk or pole labels only while the
    # walker is in it
    thin_static_hold_s: float | None = 1.0
    # ... and except one the scans' rays have crossed in more than this many scans since its
    # last hit (None: no such limit): a pole or a trunk in view is hit again before many scans
    # see through its voxel, what a walker left is seen through scan after scan
    thin_static_crossings: int | None = 4
    # what free space flags of a mover is spread over its cluster: the points of movable
    # classes in touching cells of cluster_link_m, when at least cluster_min_seeds of them and
    # cluster_min_fraction of the cluster are flagged (tisem/dynamic_clusters.py); its flagged
    # points still end rays
    dynamic_clusters: bool = True
    cluster_link_m: float = 0.4
    cluster_min_seeds: int = 10
    cluster_min_fraction: float = 0.1
    # the points of thin classes that cannot move (pole, traffic-sign, trunk) join the clusters
    # they touch without counting for either test: the network calls parts of a walker pole or
    # trunk, and those parts move with it
    cluster_thin_classes: bool = False
    # live window (toroidal storage; blocks outside the box leave the field)
    window_xy_m: float = 100.0  # half-size of the live window around the sensor; must
    # hold max_range + kernel reach + 0.8 m. 100 m keeps even
    # the densest stretch of the synthetic loop at <= 58k
    # blocks (docs/long_drive.md)
    window_z_m: float = 24.0
    max_live_blocks: int = 65_536  # hard cap on live 4^3 leaf blocks (~5.6 KB each, ~8.2 KB
    # with class centroids; compact_counters: 1.5 / 4.1 KB and
    # 80 B per live voxel). taichi 1.7.4 maps a 2nd 1 GiB host
    # chunk (unsafe: its allocator bug) at 147,456 live blocks,
    # 106,482 with class centroids, measured (docs/long_drive.md);
    # this leaves a third of that or more for a scan's growth
    # the live voxels' counters only, behind a pointer per voxel (a block holds ~7 live voxels
    # of 64, and stores counters for all 64 without it): ~20 % less memory on a long drive, 40 %
    # fewer page faults while the map grows into new space, but 3-10 % more time per scan on a
    # large live map (docs/long_drive.md). The map is the same bit for bit.
    compact_counters: bool = False
    store_dir: str | None = None  # where the host store keeps the voxels that left the
    # window (~35 B each, in an unnamed temp file that goes
    # with the process); None: the system temp dir. A place
    # on this machine, not part of the map: resuming a
    # checkpoint uses the run's, not the saved one

    def validate(self) -> None:
        """Every field against its rule (`MAPPER_RULES`), the rules between fields, then the
        sizes the map would be built with (`tisem.geometry.MapGeometry`); ConfigError."""
        check_fields(self, MAPPER_RULES)
        if self.min_range_m >= self.max_range_m:
            raise ConfigError(
                f"min_range_m = {self.min_range_m:g}: must be below max_range_m "
                f"= {self.max_range_m:g}"
            )
        if self.min_z_m >= self.max_z_m:
            raise ConfigError(
                f"min_z_m = {self.min_z_m:g}: must be below max_z_m = {self.max_z_m:g}"
            )
        if self.ell_min_m > self.ell_max_m:
            raise ConfigError(
                f"ell_min_m = {self.ell_min_m:g}: must not exceed ell_max_m = {self.ell_max_m:g}"
            )
        both = [c for c in self.vehicle_classes if c in self.thin_classes]
        if both:
            raise ConfigError(
                f"vehicle_classes = {self.vehicle_classes}: {', '.join(both)} is in "
                f"thin_classes too; a class's evidence takes one cap"
            )
        if self.empty_evidence > self.occupancy_cap:
            raise ConfigError(
                f"empty_evidence = {self.empty_evidence:g}: must not exceed "
                f"occupancy_cap = {self.occupancy_cap:g}"
            )
        check_geometry(self)

    # the kernel length bounds that the chosen mode actually uses
    @property
    def uses_kernel(self) -> bool:
        return self.mode != "csm"

    @property
    def adaptive(self) -> bool:
        return self.mode in ("st", "adaptive", "spatial")

    @property
    def reach_m(self) -> float:
        """The largest kernel length any voxel can have in this mode."""
        if not self.uses_kernel:
            return 0.0
        return self.ell_max_m if self.adaptive else self.ell_fixed_vox * self.resolution_m

    @property
    def movable_tau_s(self) -> float:
        """tau of the movable classes (the per-class decay; decay_tau_s outside st mode)."""
        if self.mode != "st" or self.tau_movable_s is None:
            return self.decay_tau_s
        return self.tau_movable_s

    @property
    def evidence_caps_m(self) -> np.ndarray:
        """(num_classes,) how far each class's evidence reaches at most, metres (inf: as far
        as the receiving voxel's kernel); csm has no kernel to cap. Names are looked up in the
        active label space; a thin class it does not have caps nothing."""
        caps = np.full(self.num_classes, np.inf)
        if self.uses_kernel:
            caps[self._class_mask(self.vehicle_classes)] = self.vehicle_cap_m
            caps[self.thin_class_mask] = self.ell_min_m
        return caps

    @property
    def thin_class_mask(self) -> np.ndarray:
        """(num_classes,) bool: the thin_classes, looked up in the active label space (a name
        it does not have marks nothing)."""
        return self._class_mask(self.thin_classes)

    @property
    def long_kernel_ids(self) -> tuple[int, ...]:
        """The long_kernel_classes' ids in the active label space (a name it does not have
        marks nothing); () outside the adaptive modes, whose lengths are fixed."""
        if not self.adaptive:
            return ()
        return tuple(int(c) for c in np.flatnonzero(self._class_mask(self.long_kernel_classes)))

    def _class_mask(self, class_list: list[str]) -> np.ndarray:
        from tisem.labels import class_names

        names = class_names()
        out = np.zeros(self.num_classes, bool)
        for name in class_list:
            if name in names and names.index(name) < self.num_classes:
                out[names.index(name)] = True
        return out

    @property
    def decay_tau_s(self) -> float:
        """tau for the exp(-dt/tau) decay: inf = plain accumulation, 0 = each scan alone."""
        return {"st": self.tau_s, "spatial": 0.0}.get(self.mode, float("inf"))


@dataclass
class RunConfig:
    """Everything a run needs: the mapper plus what feeds and scores it."""

    mapper: MapperConfig = field(default_factory=MapperConfig)
    input: str = "predictions"  # predictions | labels: which label files feed the map
    first: int = 0
    last: int | None = None  # inclusive
    online_eval: bool = True


# what each field may hold (tisem/config_rules.py); ranges wider than any sensible value, the
# sizes the map is built with are checked by `check_geometry`
MAPPER_RULES = {
    "mode": Choice(MODES),
    "resolution_m": Number(float, 0.01, 10.0, low_open=False, unit="m"),
    # the kernels keep a scan voxel's classes as the bits of an int32
    "num_classes": Number(int, 2, MAX_CLASSES),
    "min_range_m": Number(float, 0.0, 1000.0, unit="m"),
    # points beyond 1 km are treated as corrupt data
    "max_range_m": Number(float, 0.0, 1000.0, low_open=True, high_open=True, unit="m"),
    "min_z_m": Number(float, -1000.0, 1000.0, unit="m"),
    "max_z_m": Number(float, -1000.0, 1000.0, unit="m"),
    "min_points": Number(int, 1, 1_000_000),
    # pseudo-counts and kernel heights beyond 1e6 swamp any evidence float32 counters can add
    "prior": Number(float, 0.0, 1.0e6),
    "sigma0": Number(float, 0.0, 1.0e6, low_open=True),
    "ell_min_m": Number(float, 0.0, 100.0, low_open=True, unit="m"),
    "ell_max_m": Number(float, 0.0, 100.0, low_open=True, unit="m"),
    "ell_fixed_vox": Number(float, 0.0, 100.0, low_open=True, unit="voxels"),
    "kernel_cutoff": Number(float, 0.0, 1.0, low_open=True),
    "point_weight": Choice(("count", "unit")),
    "thin_classes": ClassNames(),
    "vehicle_classes": ClassNames(),
    "vehicle_cap_m": Number(float, 0.0, 100.0, low_open=True, unit="m"),
    "long_kernel_classes": ClassNames(),
    "long_kernel_share": Number(float, 0.0, 1.0, low_open=True),
    "long_kernel_min_neighbours": Number(int, 0, 24),
    "query_blend": Choice(QUERY_BLENDS, off_word="off"),
    # the blend reads the (2 R / resolution + 1)^3 voxels around a point: a few metres at most
    "query_radius_m": Number(float, 0.0, 5.0, low_open=True, unit="m"),
    "class_centroids": Flag(),
    "compact_counters": Flag(),
    "centroid_ratio": Number(float, 0.0, 1.0),
    # 1/tau is a float32 in the kernels; below 1 us every decay is exp(-1e5) = 0 anyway (mode
    # spatial), and tau = inf is mode adaptive
    "tau_s": Number(float, 1.0e-6, 1.0e12, unit="s"),
    "tau_movable_s": Number(float, 1.0e-6, 1.0e12, unit="s", optional=True),
    "free_space": Flag(),
    "spare_beside_unseen": Flag(),
    "spare_static_beside_own": Flag(),
    "spare_thin_static": Flag(),
    "thin_static_hold_s": Number(float, 0.0, 1.0e6, unit="s", optional=True),
    "thin_static_crossings": Number(int, 0, 1_000_000, optional=True),
    "dynamic_clusters": Flag(),
    "cluster_link_m": Number(float, 0.05, 5.0, unit="m"),
    "cluster_min_seeds": Number(int, 1, 1_000_000),
    "cluster_min_fraction": Number(float, 0.0, 1.0),
    "cluster_thin_classes": Flag(),
    "free_margin_m": Number(float, 0.0, 100.0, unit="m"),
    "free_ray_stride": Number(int, 1, 1_000_000),
    "free_margin_fraction": Number(float, 0.0, 1.0),
    "empty_evidence": Number(float, 0.0, 1.0e6, low_open=True),
    "occupancy_cap": Number(float, 0.0, 1.0e6, low_open=True),
    "seen_empty_s": Number(float, 0.0, 1.0e6, unit="s"),
    "window_xy_m": Number(float, 0.0, 1.0e5, low_open=True, unit="m"),
    "window_z_m": Number(float, 0.0, 1.0e5, low_open=True, unit="m"),
    "max_live_blocks": Number(int, 1, 2**31 - 1),
    "store_dir": Folder(),
}

# a live window of 5 km at 0.2 m voxels (2^29 top cells of the SNode tree) takes 1.2 GB when the
# map is built, measured; more is refused before any field exists
MAX_TOP_CELLS = 2**29

RUN_RULES = {
    "mapper": None,  # a section: its own rules
    "input": Choice(INPUTS),
    "first": Number(int, 0, 2**62),
    "last": Number(int, 0, 2**62, optional=True),
    "online_eval": Flag(),
}


def check_geometry(cfg: MapperConfig) -> None:
    """Whether a map of `cfg`'s sizes can be built: the live window holds a scan and its
    kernel reach, the scan's table fits, the kernel reach fits the table's margin
    (`MapGeometry.from_config` holds those rules); the window's storage stays within memory
    and within the store's key range."""
    from tisem.geometry import MapGeometry
    from tisem.kernels.layout import TOP
    from tisem.store_segments import KEY_LIMIT

    try:
        geometry = MapGeometry.from_config(cfg)
    except ValueError as exc:
        reason = str(exc)
        if reason.startswith("kernel reach"):
            key = "ell_max_m" if cfg.adaptive else "ell_fixed_vox"
            reason = (
                f"{key} = {getattr(cfg, key):g} at resolution_m = {cfg.resolution_m:g}: {reason}"
            )
        raise ConfigError(reason) from None
    windows = f"window_xy_m = {cfg.window_xy_m:g} / window_z_m = {cfg.window_z_m:g}"
    top_cells = int(np.prod([n // TOP for n in geometry.storage_extent]))
    if top_cells > MAX_TOP_CELLS:
        raise ConfigError(
            f"{windows} at resolution_m = {cfg.resolution_m:g}: the live "
            f"window's storage needs {top_cells:,} top cells; tisem takes at most "
            f"{MAX_TOP_CELLS:,} (1.2 GB): lower the window sizes or raise "
            f"resolution_m"
        )
    if int(geometry.window_half_vox.max()) * 4 >= KEY_LIMIT:
        raise ConfigError(
            f"{windows}: the live window must stay under "
            f"{KEY_LIMIT // 4 * cfg.resolution_m:,.0f} m at resolution_m = "
            f"{cfg.resolution_m:g} (a quarter of the map's key range)"
        )


def check_run_config(cfg: RunConfig) -> None:
    """Every field of `cfg` (its mapper section included) against its rule; ConfigError."""
    check_fields(cfg, RUN_RULES)
    if cfg.last is not None and cfg.last < cfg.first:
        raise ConfigError(f"last = {cfg.last}: must not be before first = {cfg.first}")
    cfg.mapper.validate()


def _apply(obj, data: dict, where: str, rules: dict) -> None:
    """Set the fields of `obj` from `data`, each value checked by its rule; `where` (a file,
    `--set`) starts every message."""
    names = {f.name for f in fields(obj)}
    for key, value in data.items():
        if key not in names:
            raise ConfigError(f"{where}: {unknown_name('key', key, sorted(names))}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"{where}: {key} must be a mapping of its keys, got {value!r}")
            _apply(current, value, f"{where}: {key}", MAPPER_RULES)
        else:
            setattr(obj, key, rules[key].check(key, value, where))


def set_value(cfg: RunConfig, assignment: str) -> None:
    """Apply one `key=value` override. Mapper keys may be given bare (`tau_s=1`) or dotted."""
    if "=" not in assignment:
        raise ConfigError(f"--set {assignment}: expected key=value")
    key, text = assignment.split("=", 1)
    path = key.strip().split(".")
    if len(path) == 1 and not hasattr(cfg, path[0]):
        path = ["mapper"] + path
    if path[0] == "mapper" and len(path) == 2:
        obj, rules = cfg.mapper, MAPPER_RULES
    elif len(path) == 1:
        obj, rules = cfg, RUN_RULES
    else:
        raise ConfigError(f"--set {assignment}: unknown key {key.strip()!r}")
    if path[-1] not in rules or rules[path[-1]] is None:
        known = sorted(k for k, rule in MAPPER_RULES.items() if rule is not None)
        others = sorted(k for k, rule in RUN_RULES.items() if rule is not None)
        if key.strip().startswith("mapper."):
            if path[-1] in others:
                raise ConfigError(
                    f"--set {assignment}: {path[-1]} is a key of the run, not of its mapper "
                    f"section: --set {path[-1]}={text}"
                )
            others = []
        raise ConfigError(f"--set {assignment}: {unknown_name('key', path[-1], known + others)}")
    value = yaml_value(text, f"--set {assignment}")
    setattr(obj, path[-1], rules[path[-1]].check(path[-1], value, "--set"))


def load_config(path: str | Path | None = None, overrides: list[str] | tuple = ()) -> RunConfig:
    """The default RunConfig, then the YAML file `path` (a whole RunConfig or just its mapper
    section), then the `key=value` overrides; validated (ConfigError)."""
    cfg = RunConfig()
    if path is not None:
        data = read_yaml(path)
        # a file may hold a whole RunConfig or just the mapper section
        if "mapper" not in data and any(k in MAPPER_RULES for k in data):
            data = {"mapper": data}
        _apply(cfg, data, str(path), RUN_RULES)
    for assignment in overrides:
        set_value(cfg, assignment)
    check_run_config(cfg)
    return cfg


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def save_config(cfg: RunConfig, path: str | Path) -> None:
    with open(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)


def mapper_config_from_dict(data: dict, where: str = "mapper") -> MapperConfig:
    """A validated MapperConfig from a dict (a checkpoint's, a map file's); ConfigError."""
    cfg = MapperConfig()
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of mapper keys, got {data!r}")
    _apply(cfg, data, where, MAPPER_RULES)
    cfg.validate()
    return cfg


def run_config_from_dict(data: dict, where: str = "run config") -> RunConfig:
    """A validated RunConfig from a dict (a checkpoint's); ConfigError."""
    cfg = RunConfig()
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of config keys, got {data!r}")
    _apply(cfg, data, where, RUN_RULES)
    check_run_config(cfg)
    return cfg
