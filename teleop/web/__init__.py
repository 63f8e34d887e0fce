"""Browser teleoperation: `teleop serve` (WebApp) on viser + mjviser.

Modules: net (host/port checks), access (the session token), sim_thread (the real-time control loop and
its snapshots), drawing (3D scene, markers, gizmos), camera_view (offscreen
camera picture), panel (buttons and figures), app (wiring and status).
"""
