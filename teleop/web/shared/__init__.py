"""What every page shares: access (token, loopback Host rule, wrong-token throttle), net (host and
port checks, URLs), stdlib_http (the stdlib servers' deadline, JSON bodies, files with Range, the
stylesheet static/teleop.css), loop_thread and cpu_pressure (background loops that yield under load)."""
