"""hmflow: batch history-matching campaigns (the application layer: CLI)."""
