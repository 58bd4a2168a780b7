"""Run by .ci/run with a virtual environment's python, outside the checkout, after installing ocv2's wheel.

Checks that the installed package (not the checkout) answers every command it needs data for: the
packaged paper configs validate, and a tiny FCP run whose partners are trained first takes the partner
stage's hyperparameters from the packaged paper self-play config (never from defaults).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

CHECKOUT = Path(sys.argv[1]).resolve()
SIZES = {
    "num_envs": 4,
    "num_steps": 32,
    "num_minibatches": 2,
    "update_epochs": 1,
    "total_timesteps": 256,
    "rew_shaping_horizon": 128,
}
TINY_FCP = {
    "env": {"layout": "cramped_room", "max_steps": 40},
    "model": {"kind": "cnn", "conv_features": [8, 8], "conv_kernels": [3, 3], "fc_dim": 16},
    "ppo": {**SIZES, "lr": 1.0e-3},
    # partner_ppo gives only sizes: every other value must come from the paper's SP config
    "population": {
        "method": "fcp",
        "num_seeds": 1,
        "fcp": {"partner_seeds": 1, "checkpoints": ["final"], "partner_ppo": SIZES},
    },
    "eval": {"episodes": 1, "gifs": 0},
    "run": {"checkpoint_every": 8, "num_checkpoints": 2},
    "archive": {"xp": False, "sa_collection": False},
}


def main() -> None:
    import cluster
    import ocv2
    import population
    from population.config import PAPER_CONFIGS

    for module in (ocv2, population, cluster):
        where = Path(module.__file__).resolve()
        assert CHECKOUT not in where.parents, f"{module.__name__} imported from the checkout: {where}"
    assert not any(Path(p or ".").resolve() == CHECKOUT for p in sys.path), f"the checkout is on sys.path: {sys.path}"
    ocv2_cli = str(Path(sys.executable).with_name("ocv2"))
    papers = sorted(str(p) for p in Path(str(PAPER_CONFIGS)).glob("*.yaml"))
    assert len(papers) >= 40, f"only {len(papers)} paper configs in the wheel"
    subprocess.run([ocv2_cli, "validate", *papers], check=True, stdout=subprocess.DEVNULL)
    print(f"wheel: ocv2 validate passed on the {len(papers)} packaged paper configs")
    from cluster.study.spec import load_study

    studies = sorted(Path(str(PAPER_CONFIGS)).parent.joinpath("studies").glob("*.yaml"))
    assert len(studies) >= 14, f"only {len(studies)} studies in the wheel"
    for study in studies:  # every run's config resolves inside the installed package
        load_study(study)
    print(f"wheel: the {len(studies)} packaged studies load")

    with tempfile.TemporaryDirectory() as tmp:
        config = Path(tmp) / "tiny_fcp.yaml"
        config.write_text(yaml.safe_dump(TINY_FCP))
        run = Path(tmp) / "run"
        subprocess.run(
            [ocv2_cli, "train", str(config), "--backend", "local", "--quiet", "--no-eval", "--out", str(run)],
            check=True,
            cwd=tmp,
        )
        stage = yaml.safe_load((run / "partners" / "config.yaml").read_text())["ppo"]
    paper = yaml.safe_load((Path(str(PAPER_CONFIGS)) / "classic_cramped_room_sp.yaml").read_text())["ppo"]
    for key, value in paper.items():
        expected = SIZES.get(key, value)
        assert stage[key] == expected, f"partner stage {key} = {stage[key]!r}, paper SP config says {expected!r}"
    print(
        f"wheel: the FCP partner stage trained with the packaged paper SP hyperparameters "
        f"(lr {stage['lr']}, ent_coef {stage['ent_coef']}, max_grad_norm {stage['max_grad_norm']})"
    )


if __name__ == "__main__":
    main()
