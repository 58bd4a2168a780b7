"""Experiment configuration: YAML parsed once into frozen, typed, validated dataclasses.

One job per module: ``schema`` (the section dataclasses and ``Config``), ``yaml_io`` (reading files,
``--set`` overrides, writing a resolved config), ``fields`` (a section's mapping -> its dataclass, with
types and numeric ranges), ``validate`` (values checked against each other), ``paper`` (the configs
shipped as package data and the paper's self-play hyperparameters), ``parse`` (all of it -> ``Config``),
and ``shards`` (splitting seeds and jobs over workers); the memory a run needs is ``population.memory``.
Every error names the offending key (``ppo.num_minibatches``) and where it came from (the file, or ``--set``).

    config = load_config("configs/quickstart.yaml", overrides=["ppo.total_timesteps=1e5"])
"""

from population.config.errors import ConfigError
from population.config.paper import (
    PACKAGED_CONFIGS,
    PAPER_CONFIGS,
    paper_config_files,
    paper_sp_ppo,
)
from population.config.parse import (
    RAY_LAUNCHER_KEYS,
    is_ray_launcher_config,
    is_study_data,
    load_config,
    load_run_config,
    parse_config,
    read_config_file,
)
from population.config.schema import (
    ACTIVATIONS,
    FCP_POOLS,
    FCP_STAGE_SEED_OFFSET,
    GRU_BACKWARDS,
    KERNELS,
    MAX_GRU_UNROLL,
    MAX_SEED,
    METHOD_TABLE,
    METHODS,
    MODEL_DEFAULTS,
    PRECISIONS,
    SECTIONS,
    ArchiveConfig,
    ClusterConfig,
    Config,
    EvalConfig,
    FCPConfig,
    Method,
    ModelConfig,
    OPConfig,
    PopulationConfig,
    PPOConfig,
    RunConfig,
    SAConfig,
    is_update_number,
)
from population.config.shards import shards, spread
from population.config.yaml_io import (
    MAX_YAML_NODES,
    apply_overrides,
    check_plain_data,
    dump_config,
    load_yaml_text,
    read_yaml,
    yaml_problem,
)

__all__ = [
    "ACTIVATIONS",
    "GRU_BACKWARDS",
    "KERNELS",
    "MAX_GRU_UNROLL",
    "FCP_POOLS",
    "FCP_STAGE_SEED_OFFSET",
    "MAX_SEED",
    "is_update_number",
    "MAX_YAML_NODES",
    "METHOD_TABLE",
    "METHODS",
    "Method",
    "MODEL_DEFAULTS",
    "PACKAGED_CONFIGS",
    "PAPER_CONFIGS",
    "PRECISIONS",
    "RAY_LAUNCHER_KEYS",
    "read_config_file",
    "SECTIONS",
    "ArchiveConfig",
    "ClusterConfig",
    "Config",
    "ConfigError",
    "EvalConfig",
    "FCPConfig",
    "ModelConfig",
    "OPConfig",
    "PPOConfig",
    "PopulationConfig",
    "RunConfig",
    "SAConfig",
    "apply_overrides",
    "check_plain_data",
    "dump_config",
    "is_ray_launcher_config",
    "is_study_data",
    "load_config",
    "load_run_config",
    "load_yaml_text",
    "paper_config_files",
    "paper_sp_ppo",
    "parse_config",
    "read_yaml",
    "shards",
    "spread",
    "yaml_problem",
]
