"""Typed, frozen configuration of every command: the schema (`schema`), its value rules (`rules`) and
YAML loading with `--set` overrides (`loading`). Import from here: `from jaxmap.config import MapConfig,
load_config`."""
from jaxmap.config.loading import (apply_overrides, config_from_args, from_dict, load_config, resolve_config,
                                   save_config, shipped_config_dir, shipped_config_path, shipped_configs, to_dict,
                                   unknown_key_message)
from jaxmap.config.rules import (CHECKS, DATA_KINDS, RULES, Rule, above, at_least, lattice_problem, one_of,
                                 strictly_within, validate, within)
from jaxmap.config.schema import (DataConfig, DecoderConfig, EvalConfig, EvidenceConfig, SubmapsConfig, GridConfig, ImtConfig, LatentMapConfig,
                                  LatentMeshConfig, MapConfig, MeshConfig, PreprocessConfig, SamplingConfig,
                                  TrainConfig, WindowConfig)
from jaxmap.config.prior import (EncoderConfig, LatentDecoderConfig, PriorConfig, PriorDataConfig, PriorModelConfig,
                                  PriorTrainConfig)
from jaxmap.config.slam import FrontEndConfig, LoopConfig, OdometryConfig, SlamConfig
from jaxmap.errors import ConfigError

__all__ = ["apply_overrides", "config_from_args", "from_dict", "load_config", "resolve_config", "save_config",
           "shipped_config_dir", "shipped_config_path", "shipped_configs",
           "to_dict", "unknown_key_message", "CHECKS", "DATA_KINDS", "RULES", "Rule", "above", "at_least",
           "lattice_problem", "one_of", "strictly_within", "validate", "within", "DataConfig",
           "DecoderConfig", "EvalConfig", "EvidenceConfig", "SubmapsConfig", "GridConfig", "ImtConfig", "LatentMapConfig", "LatentMeshConfig",
           "MapConfig", "MeshConfig", "PreprocessConfig", "SamplingConfig", "TrainConfig", "WindowConfig",
           "FrontEndConfig", "LoopConfig", "OdometryConfig", "SlamConfig", "EncoderConfig", "LatentDecoderConfig", "PriorConfig", "PriorDataConfig",
           "PriorModelConfig", "PriorTrainConfig", "ConfigError"]
