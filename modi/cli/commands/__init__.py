"""CLI subcommands. Each module here defines ``register(subparsers)``; ``modi.cli`` finds them all."""
