"""The `teleop` command line: one module per group of subcommands; the only place that installs signal handlers."""
