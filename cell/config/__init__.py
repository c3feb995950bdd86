"""The cell's configuration: one TOML file, validated strictly before any device is touched.

- :mod:`~cell.config.schema`: the tables and keys, each error naming the offending key;
- :mod:`~cell.config.checks`: commissioning checks beyond the schema (the integrator's mistakes);
- :mod:`~cell.config.tokens`: the API token rules for real hardware;
- :mod:`~cell.config.endpoints`: where the PLC and robot-program interfaces listen.
"""

from cell.config.schema import CellConfig, ConfigError, load_config, parse_config

__all__ = ["CellConfig", "ConfigError", "load_config", "parse_config"]
