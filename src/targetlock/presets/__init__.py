"""Named endoscope presets (``NAME.toml`` beside this file); the names live here so listing them is cheap."""

PRESETS = ("calibrated", "uncalibrated", "looped-shaft")
