"""The dose–response sweep (``robustbench3d sweep``): how big and how colourful a roof object must be.

:mod:`~robustbench3d.sweep.grid` names the points (object families: icosphere level x radius, the seed's
``l2-r0.40`` always among them), :mod:`~robustbench3d.sweep.train` trains (or reuses, or resumes) one universal
object per point with ``attack train``'s :func:`~robustbench3d.attacks.train_run.train_universal` as jobs on
worker processes or Ray (:mod:`~robustbench3d.sweep.jobs`), :mod:`~robustbench3d.sweep.run` scores every object,
the clean control and the benign sphere of each radius in one benchmark run, :mod:`~robustbench3d.sweep.analysis`
reads the run's cells into the dose–response rows with their bootstrap intervals, and
:mod:`~robustbench3d.sweep.output` writes ``sweep.json``, ``sweep.csv``, ``sweep.md`` and ``sweep.png``.
"""
