"""Embedded default dataset: procedural driving scenes written in the KITTI layout.

Entry points (imported lazily, so that ``robustbench3d.commands.data_synth`` stays light):

* :func:`robustbench3d.synth.frame.generate_frame` -- one frame (image, scan, calib, labels and the
  scene behind them) as a pure function of (seed, frame index);
* :func:`robustbench3d.synth.writer.generate_dataset` -- a resumable, parallel KITTI-layout dataset;
* :func:`robustbench3d.synth.layout.sample_scene` -- a scene alone (road, objects, meshes, lighting).

Modules: ``road`` (road geometry, ground), ``layout`` (object placement), ``vehicles``, ``people``,
``clutter``, ``mesh`` (meshes), ``materials``, ``calibs`` (real KITTI calibrations), ``scene``
(scene container, KITTI poses), ``raytrace`` (Embree), ``lidar``, ``camera``, ``annotate`` (labels),
``frame``, ``writer``, ``cli``, ``bench``.
"""

#: Defaults of ``robustbench3d data synth``, which are also the fixed parameters of the embedded
#: dataset a benchmark generates when no ``--data`` is given (:data:`robustbench3d.datasets.EMBEDDED`).
DEFAULT_FRAMES = 2000
DEFAULT_SEED = 0
DEFAULT_VAL_FRACTION = 0.5
