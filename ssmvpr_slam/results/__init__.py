"""What a run leaves behind: its records assembled (`assembly`), its files (`writers`,
`mcap_output`), its metrics and end-of-run table (`metrics`, `summary`), and the timestamped
folders they go in (`run_folder`)."""
