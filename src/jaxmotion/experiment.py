"""Experiments from TOML configs: load, run, and read back results folders; multi-stage
(seriatim) experiments, each stage starting where the previous stage's best motion ended;
composite motions (`python -m jaxmotion compose`).

This is the config/IO layer (the library core never touches disk); `python -m jaxmotion`
is built on it.
"""

from ._cli.cache import default_cache_dir as default_cache_dir
from ._cli.cache import use_compilation_cache as use_compilation_cache
from ._cli.compose import ComposeConfig as ComposeConfig
from ._cli.compose import check_compose_config as check_compose_config
from ._cli.compose import parse_compose_config as parse_compose_config
from ._cli.compose import phase_measures as phase_measures
from ._cli.compose import phase_trajectories as phase_trajectories
from ._cli.compose import read_compose_config as read_compose_config
from ._cli.compose import run_compose as run_compose
from ._cli.config import ConfigError as ConfigError
from ._cli.config import Experiment as Experiment
from ._cli.config import default_config_path as default_config_path
from ._cli.config import load_config as load_config
from ._cli.config import parse_config as parse_config
from ._cli.results import Interrupted as Interrupted
from ._cli.results import controller_from_dict as controller_from_dict
from ._cli.results import controller_to_dict as controller_to_dict
from ._cli.results import load_result as load_result
from ._cli.results import load_stages as load_stages
from ._cli.results import read_history_csv as read_history_csv
from ._cli.results import replay_stages as replay_stages
from ._cli.results import run_check as run_check
from ._cli.results import run_experiment as run_experiment
from ._cli.results import run_sequence_check as run_sequence_check
from ._cli.results import start_where as start_where
from ._sim.trajectory import concatenate_trajectories as concatenate_trajectories

__all__ = [
    "ComposeConfig",
    "ConfigError",
    "Experiment",
    "Interrupted",
    "check_compose_config",
    "concatenate_trajectories",
    "controller_from_dict",
    "controller_to_dict",
    "default_cache_dir",
    "default_config_path",
    "load_config",
    "load_result",
    "load_stages",
    "parse_compose_config",
    "parse_config",
    "phase_measures",
    "phase_trajectories",
    "read_compose_config",
    "read_history_csv",
    "replay_stages",
    "run_check",
    "run_compose",
    "run_experiment",
    "run_sequence_check",
    "start_where",
    "use_compilation_cache",
]
