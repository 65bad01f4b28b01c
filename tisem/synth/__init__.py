"""Synthetic labelled LiDAR sequences: a procedural street, a 64-beam LiDAR, noisy labels.

- `route`: the road as straight and circular segments, by arc length
- `shapes`: the primitives (boxes, cylinders, ellipsoids) the world is made of
- `scene`: the routes driven, the scene along them in lazily built 50 m tiles, the moving actors
- `lidar`: the spinning LiDAR, ray-cast in numpy
- `noise`: "network" predictions made from ground truth
- `sequence`: frames, `Scan`s and SemanticKITTI folders
- `mcap_log`: a small analytic ROS 2 recording for the MCAP reader's tests and benchmark
"""

from tisem.synth.sequence import (
    SyntheticSequence,
    SynthFrame,
    iter_synthetic,
    to_scan,
    write_semantickitti,
)

__all__ = ["SynthFrame", "SyntheticSequence", "iter_synthetic", "to_scan", "write_semantickitti"]
