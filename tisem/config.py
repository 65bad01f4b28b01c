"""Configuration: a dataclass per concern, loaded from YAML, overridable with `key=value`.

Every results folder gets the resolved config (`config.yaml`), so a run can be repeated.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields
from pathlib import Path

import yaml

MODES = ("st", "adaptive", "spatial", "bki", "csm")


@dataclass
class MapperConfig:
    """The method's parameters (SPEC §1). Lengths in metres unless the name says voxels."""

    mode: str = "st"                 # st | adaptive | spatial | bki | csm
    resolution_m: float = 0.2        # voxel edge
    num_classes: int = 20
    # 1. preprocess: points outside [min_range, max_range] or the height band are dropped
    min_range_m: float = 2.0         # the ego vehicle's own returns
    max_range_m: float = 80.0
    min_z_m: float = -4.0            # height band relative to the sensor (region of interest)
    max_z_m: float = 8.0
    # 3. redundant voxel filtering
    min_points: int = 1
    # 4.-6. entropy, adaptive length, sparse kernel (defaults measured: README "Parameters")
    prior: float = 2.0               # pseudo-count added to every class before the entropy is
                                     # taken: entropy then falls only as evidence piles up, so
                                     # sparse, young or contradicted voxels get long kernels
    sigma0: float = 1.0
    ell_min_m: float = 0.4
    ell_max_m: float = 1.2
    ell_fixed_vox: float = 4.0       # bki: fixed kernel length, in voxels
    point_weight: str = "count"      # count: a training voxel weighs by its points; unit: once
    # 8. temporal fusion
    tau_s: float = 5.0               # decay time constant (st mode)
    # live window (toroidal storage; blocks outside the box leave the field)
    window_xy_m: float = 100.0       # half-size of the live window around the sensor; must
                                     # hold max_range + kernel reach + 0.8 m. 100 m keeps even
                                     # the densest stretch of the synthetic loop at <= 58k
                                     # blocks (docs/long_drive.md)
    window_z_m: float = 24.0
    max_live_blocks: int = 65_536    # hard cap on live 4^3 leaf blocks (~5.6 KB each). taichi
                                     # 1.7.4 maps a 2nd 1 GiB host chunk (unsafe: its allocator
                                     # bug) at 147,456 live blocks, measured (docs/long_drive.md);
                                     # this leaves over half of that for a scan's growth
    store_dir: str | None = None     # where the host store keeps the voxels that left the
                                     # window (~35 B each, in an unnamed temp file that goes
                                     # with the process); None: the system temp dir. A place
                                     # on this machine, not part of the map: resuming a
                                     # checkpoint uses the run's, not the saved one

    def validate(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if self.point_weight not in ("unit", "count"):
            raise ValueError(f"point_weight must be 'unit' or 'count', got {self.point_weight!r}")
        positive = ("resolution_m", "max_range_m", "sigma0", "ell_min_m", "ell_max_m",
                    "ell_fixed_vox", "tau_s", "window_xy_m", "window_z_m")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.ell_min_m > self.ell_max_m:
            raise ValueError(f"ell_min_m ({self.ell_min_m}) > ell_max_m ({self.ell_max_m})")
        if self.min_range_m < 0 or self.min_range_m >= self.max_range_m:
            raise ValueError("need 0 <= min_range_m < max_range_m")
        if self.max_range_m >= 1000:
            raise ValueError("max_range_m must be < 1000 m (points beyond 1 km are treated as "
                             "corrupt)")
        if self.min_z_m >= self.max_z_m:
            raise ValueError("need min_z_m < max_z_m")
        if self.prior < 0:
            raise ValueError("prior must be >= 0")
        if self.num_classes < 2:
            raise ValueError("num_classes must be >= 2")

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
    def decay_tau_s(self) -> float:
        """tau for the exp(-dt/tau) decay: inf = plain accumulation, 0 = each scan alone."""
        return {"st": self.tau_s, "spatial": 0.0}.get(self.mode, float("inf"))


@dataclass
class RunConfig:
    """Everything a run needs: the mapper plus what feeds and scores it."""

    mapper: MapperConfig = field(default_factory=MapperConfig)
    input: str = "predictions"       # predictions | labels: which label files feed the map
    first: int = 0
    last: int | None = None          # inclusive
    online_eval: bool = True


def _coerce(value: str, current):
    """Parse a `--set` value with YAML rules, keeping the field's type where obvious."""
    parsed = yaml.safe_load(value)
    if isinstance(current, bool) or current is None:
        return parsed
    if isinstance(current, float) and isinstance(parsed, int):
        return float(parsed)
    return parsed


def _apply(obj, data: dict, where: str) -> None:
    names = {f.name: f for f in fields(obj)}
    for key, value in data.items():
        if key not in names:
            raise KeyError(f"{where}: unknown key {key!r}; known: {sorted(names)}")
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ValueError(f"{where}: {key} must be a mapping")
            _apply(current, value, f"{where}.{key}")
        else:
            setattr(obj, key, value)


def set_value(cfg: RunConfig, assignment: str) -> None:
    """Apply one `key=value` override. Mapper keys may be given bare (`tau_s=1`) or dotted."""
    if "=" not in assignment:
        raise ValueError(f"--set expects key=value, got {assignment!r}")
    key, value = assignment.split("=", 1)
    path = key.strip().split(".")
    if len(path) == 1 and not hasattr(cfg, path[0]):
        path = ["mapper"] + path
    obj = cfg
    for part in path[:-1]:
        obj = getattr(obj, part, None)
        if not dataclasses.is_dataclass(obj):
            raise KeyError(f"--set {assignment}: {part!r} is not a config section")
    if not hasattr(obj, path[-1]) or dataclasses.is_dataclass(getattr(obj, path[-1])):
        raise KeyError(f"--set {assignment}: unknown key {key!r}")
    setattr(obj, path[-1], _coerce(value, getattr(obj, path[-1])))


def load_config(path: str | Path | None = None, overrides: list[str] | tuple = ()) -> RunConfig:
    cfg = RunConfig()
    if path is not None:
        with open(path) as f:
            data = yaml.safe_load(f) or {}
        if not isinstance(data, dict):
            raise ValueError(f"{path}: expected a mapping at the top level")
        # a file may hold a whole RunConfig or just the mapper section
        if "mapper" not in data and any(k in {f.name for f in fields(MapperConfig)} for k in data):
            data = {"mapper": data}
        _apply(cfg, data, str(path))
    for assignment in overrides:
        set_value(cfg, assignment)
    cfg.mapper.validate()
    return cfg


def to_dict(cfg) -> dict:
    return dataclasses.asdict(cfg)


def save_config(cfg: RunConfig, path: str | Path) -> None:
    with open(path, "w") as f:
        yaml.safe_dump(to_dict(cfg), f, sort_keys=False)


def mapper_config_from_dict(data: dict) -> MapperConfig:
    cfg = MapperConfig()
    _apply(cfg, data, "mapper")
    cfg.validate()
    return cfg
