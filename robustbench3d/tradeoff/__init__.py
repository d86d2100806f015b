"""The speed/accuracy trade of the harness, measured (``robustbench3d tradeoff``).

:mod:`~robustbench3d.tradeoff.sweeps` defines one-knob-at-a-time sweeps around the default setting,
:mod:`~robustbench3d.tradeoff.measure` times and scores their clean and attacked cells on the same
frames, :mod:`~robustbench3d.tradeoff.analysis` turns them into |ΔAP| against each sweep's
highest-fidelity point with paired bootstrap intervals and Pareto fronts, and
:mod:`~robustbench3d.tradeoff.output` writes the CSV, Markdown and figure.
"""
