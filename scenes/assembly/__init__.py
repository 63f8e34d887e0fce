"""Putting a scene together: robots, the arena and its layout, the compiled scene, mesh collision parts, framing."""
