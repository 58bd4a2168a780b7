"""One tiny trained run shared by tests/test_policy.py and tests/test_crossplay.py (trained once per
pytest process). configs/smoke.yaml on overcookedv2_demo with 100-step episodes: its kitchen has a
button that costs 5 when pressed, so even barely trained policies score non-zero, policy-dependent
returns -- cross-play comparisons then compare real numbers, not zeros."""

from __future__ import annotations

from pathlib import Path

from cluster.cli import main

SMOKE = str(Path(__file__).resolve().parents[1] / "configs" / "smoke.yaml")
DEMO = ("env.layout=overcookedv2_demo", "env.max_steps=100")


def train(out, *overrides) -> int:
    args = ["train", SMOKE, "--out", str(out), "--quiet", "--backend", "local", "--no-eval"]
    for item in (*DEMO, *overrides):
        args += ["--set", item]
    return main(args)


def shared_run(tmp_path_factory) -> Path:
    """The demo run (2 seeds, checkpoints at updates 0, 2, 4), trained on first use."""
    run = tmp_path_factory.getbasetemp() / "policy_demo_run"
    if not (run / "checkpoints" / "seed_1" / "update_0000004.msgpack").exists():
        assert train(run) == 0
    return run
