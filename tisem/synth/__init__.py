"""Synthetic labelled LiDAR sequences: a procedural street, a 64-beam LiDAR, noisy labels.

- `scene`: the route, the scene along it in lazily built 50 m tiles, the moving actors
- `lidar`: the spinning LiDAR, ray-cast in numpy
- `noise`: "network" predictions made from ground truth
- `sequence`: frames, `Scan`s and SemanticKITTI folders
"""
from tisem.synth.sequence import (SynthFrame, SyntheticSequence, iter_synthetic, to_scan,
                                  write_semantickitti)

__all__ = ["SynthFrame", "SyntheticSequence", "iter_synthetic", "to_scan", "write_semantickitti"]
