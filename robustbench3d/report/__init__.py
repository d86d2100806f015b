"""``robustbench3d report``: the leaderboard of one or more runs as ``leaderboard.html`` (self-contained) and
``leaderboard.md``, with figures, the transfer matrix and scene figures (see :mod:`robustbench3d.report.cli`).

Modules: :mod:`.data` (runs read back, comparable sections, tables, the transfer matrix), :mod:`.figures`
(matplotlib), :mod:`.scenes` (frames drawn clean and attacked by ``show``'s renderer), :mod:`.page` (HTML and
markdown), :mod:`.cli` (the command). Standard library only at import.
"""
