"""hmepol's Hydra launcher plugin: sweep jobs that differ only in their seed run as populations."""
