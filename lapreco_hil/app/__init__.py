"""The application layer: what the lapreco commands do, callable without the CLI."""
