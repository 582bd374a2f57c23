"""Settings: the composed model and its loading (`slam`), the run-time sections owned by the
application (`pipeline`, `map`), the shipped presets, renamed keys (`retired`) and the settings
shown in front (`in_front`). Kept empty so that `presets` loads without the models."""
