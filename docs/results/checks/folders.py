"""Where the checks read: docs/results/, its study folders, and the layout file the geometry check parses."""

from __future__ import annotations

from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1]  # docs/results/
REPOSITORY = RESULTS.parents[1]  # what the paths in a cross-play's summary.json are relative to
LAYOUTS = REPOSITORY / "ocv2" / "layouts.py"
CR = RESULTS / "table1_coord_ring"
GCS = RESULTS / "reduced_gcs"
SP10 = RESULTS / "table1_coord_ring_sp10"
SA10 = RESULTS / "table1_coord_ring_sa10"
FC10 = RESULTS / "table1_forced_coord_sp10"
FC_SA10 = RESULTS / "table1_forced_coord_sa10"  # its SA half at the same budget
GPU_CR = RESULTS / "gpu_coord_ring_sp"  # Table 1 Coordination Ring SP on the paper's 10M schedule, trained on a GPU
GPU410 = RESULTS / "gpu_coord_ring_sp_update410"  # that study at update 410 (6.7M), cross-played on the CPU
CC10 = RESULTS / "table1_counter_circuit_sp10"  # Table 1 Counter Circuit SP, 10 seeds, the 10M schedule truncated at 3M
CC_SA10 = RESULTS / "table1_counter_circuit_sa10"  # its SA half at the same budget
CC10_6M = RESULTS / "table1_counter_circuit_sp10_6m"  # the same SP seeds trained on to 6M (--extend)
CC_SA10_6M = RESULTS / "table1_counter_circuit_sa10_6m"  # the same SA seeds trained on to 6M (--extend)
CRM10 = RESULTS / "table1_cramped_room_sp10"  # Table 1 Cramped Room SP (the control), 10 seeds, truncated at 3M
CRM_SA10 = RESULTS / "table1_cramped_room_sa10"  # its SA half at the same budget
AA10 = RESULTS / "table1_asymm_advantages_sp10"  # Table 1 Asymm. Advantages SP (the other control), 10 seeds, at 3M
