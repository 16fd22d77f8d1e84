"""Configuration: YAML groups under this folder, merged into the dataclass schemas of :mod:`conf.schema`."""
