"""A PointPillars-style LiDAR-only Car detector (victim ``pointpillars``; ONNX twin ``pointpillars-onnx``).

* :mod:`.pillars` -- the pillar grid, the assignment of points to pillars (numpy) and the per-point features
  (torch, differentiable; and numpy, what ``detect`` uses).
* :mod:`.config` / :mod:`.model` -- the network: pillar PointNet, BEV scatter, 2D backbone, centre head.
* :mod:`.targets` -- box conventions (KITTI rect labels <-> velodyne boxes), heatmap targets and decoding.
* :mod:`.glue` -- scan -> network inputs -> KITTI detections, shared by the torch victim and the ONNX twin.
* :mod:`.detector` -- the victim: ``detect`` and ``target_scores``.
* :mod:`.training` -- the training task of ``robustbench3d victims train-pointpillars``.

The ONNX export and twin live with the other ONNX victims: :mod:`robustbench3d.victims.onnx.pointpillars_export`
and :mod:`robustbench3d.victims.onnx.pointpillars`.
"""
