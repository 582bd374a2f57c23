"""A run's checkpoints: written as it goes (`saving`), read back checked (`loading`, `record`),
replayed into a fresh system (`replay`), and what a resumed run may change (`resume`)."""
