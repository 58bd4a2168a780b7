"""The configs shipped inside the package (``population/config/files``; ``configs/`` in a checkout links
there), and the paper self-play hyperparameters an FCP partner stage defaults to.

They are package data read through ``importlib.resources``, so a wheel install finds them as a source
checkout does; a missing or unreadable file is an error, never a silent fallback to defaults.
"""

from __future__ import annotations

import functools
from importlib import resources
from importlib.resources.abc import Traversable

import yaml

from population.config.errors import ConfigError
from population.config.fields import parse_section
from population.config.schema import PPOConfig
from population.config.yaml_io import load_yaml_text

#: Every config shipped with ocv2: quickstart.yaml, smoke.yaml, paper/ (the paper's experiments), cluster/.
PACKAGED_CONFIGS: Traversable = resources.files("population.config") / "files"
#: The paper's experiments, one YAML each (docs/REPRODUCING.md).
PAPER_CONFIGS: Traversable = PACKAGED_CONFIGS / "paper"


def paper_config_files() -> list[Traversable]:
    """The shipped paper configs, by name; a ConfigError if the package lacks them (a broken install)."""
    files = (
        sorted((f for f in PAPER_CONFIGS.iterdir() if f.name.endswith(".yaml")), key=lambda f: f.name)
        if PAPER_CONFIGS.is_dir()
        else []
    )
    if not files:
        raise ConfigError(
            f"the paper configs that ship with ocv2 are missing ({PAPER_CONFIGS}): the installation "
            "is incomplete; reinstall ocv2"
        )
    return files


@functools.cache
def paper_sp_ppo(layout: str, model_kind: str) -> PPOConfig | None:
    """The ppo section of the paper's self-play config for ``layout`` and ``model_kind`` (None: there is none)."""
    found = {}
    for file in paper_config_files():
        try:
            raw = load_yaml_text(file.read_text(encoding="utf-8")) or {}
        except (OSError, UnicodeDecodeError, yaml.YAMLError) as error:
            raise ConfigError(f"{file}: the packaged paper config cannot be read ({error}); reinstall ocv2") from None
        pop, env, model = raw.get("population") or {}, raw.get("env") or {}, raw.get("model") or {}
        if pop.get("method") == "sp" and env.get("layout") == layout and model.get("kind") == model_kind:
            found[file.name] = parse_section(f"{file.name}: ppo", PPOConfig, raw.get("ppo"))
    if len(set(found.values())) > 1:
        raise ConfigError(
            f"population.fcp.partner_ppo: paper self-play configs {', '.join(found)} disagree "
            f"for layout {layout!r}; set population.fcp.partner_ppo"
        )
    return next(iter(found.values()), None)
