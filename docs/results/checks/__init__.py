"""The checks of docs/RESULTS.md, which docs/results/check_results.py runs: one module per part of the page, on
top of the modules that read the page and the data (read check_results.py's docstring first).

Each module imports only from the modules listed before it (no cycles):

- folders.py: where the committed files are; page.py: reading the page's tagged spans and their numbers;
  registry.py: ``CHECKS`` and ``@check("NAME")``;
- data.py: the committed files read into numbers; four_seed_bootstrap.py: every resample of a 4-seed matrix;
  coord_ring_layout.py: Coordination Ring's ring, parsed from ocv2/layouts.py;
- four_seed_studies.py and ten_seed_studies.py: what several sections read the same way from the 4-seed and the
  10-seed studies;
- comparison.py: ``compare``, the page against the checks;
- the checks, by part of the page: opening_sections.py (the top of the page, intervals at 4 seeds, what is being
  run, the claims table), coord_ring_4_seeds.py, coord_ring_10_seeds.py, gpu_coord_ring.py, forced_coord.py,
  counter_circuit.py, grounded_coord_simple.py, and ten_seed_rows.py (the rows every 10-seed study has).

A new check goes into the module of its part of the page (a new study's section: a module of its own, added to
``CHECK_MODULES`` in check_results.py); a helper that a second module needs moves down into four_seed_studies.py,
ten_seed_studies.py or data.py rather than being imported from beside a check.
"""
