"""The runner layer around the core: it owns files, signals, progress and pacing (`runner`,
`pipeline`, `realtime`, `stop_signals`, `staging_lock`), the live view, the demo's simulated
logs and the `optimize` command."""
