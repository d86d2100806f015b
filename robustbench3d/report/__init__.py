"""``robustbench3d report``: the leaderboard of one or more runs as ``leaderboard.html`` (self-contained) and
``leaderboard.md``, with the worst case, figures, the transfer matrix and scene figures (see
:mod:`robustbench3d.report.build`).

Modules: :mod:`.data` (runs read back, comparable sections, tables, the transfer matrix, cells merged or left
out), :mod:`.worst` (victims ranked by their worst attacked AP), :mod:`.table1` (the seed paper's Table 1 beside
the measured rows), :mod:`.view` (columns and formats both pages share), :mod:`.figures` (matplotlib),
:mod:`.scenes` (frames drawn clean and attacked by ``show``'s renderer), :mod:`.page` (HTML, a Jinja2 template in
``templates/``), :mod:`.mdpage` (markdown, tables by tabulate), :mod:`.cli` (the command). Standard library only
at import.
"""
