"""Scene presets for stillbox-gen: one TOML file per preset (see docs/FORMAT.md for the keys)."""
