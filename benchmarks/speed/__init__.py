"""Speed: where the time of a registration, a command or a training step goes, and what each speed-up saved."""
