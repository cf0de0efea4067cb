"""Paper reproductions and modelling studies, apart from the benchmark problems.

A study builds models from the physics in :mod:`problems` (nothing re-derived here), runs
its analysis and writes tables (CSV) and figures (SVG) into one output folder; the suite
runner stores them as the study's report section. Every study has one interface,
``run(out: pathlib.Path) -> dict[str, pandas.DataFrame]`` (the tables, keyed by file stem),
and runs alone as ``python -m studies.MODULE --out DIR``. A suite names a study by its key
in :data:`STUDIES` (``study = "flexible-modal"``).

``flexible``
    The flexible spacecraft's finite-element model (``pyfe3d`` shells), its modal sets
    and their synthesis, modal cost analysis and internal balancing.
``flexible_modal``
    The study that runs them: the seed's Tables 1 and 2 analogues, and the reduced model
    stored for the ``flexible-spacecraft`` problem (``--regenerate``).
``seed_sps``
    The first seed's reduced SPS receiver: its setting and a step-size sweep, the analogues
    of its Figs. 3 and 4, and the verdict on its claim.
"""

#: Registered studies: name -> ``"module:function"`` with ``function(out) -> dict``.
STUDIES: dict[str, str] = {
    "flexible-modal": "studies.flexible_modal:run",
    "seed-sps": "studies.seed_sps:run",
}
