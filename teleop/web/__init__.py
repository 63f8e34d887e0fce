"""Browser teleoperation: `teleop serve` (WebApp) and the replay viewer, on viser + mjviser.

Modules: net (host/port checks), access (the token gate both servers start behind), sim_thread (the real-time control loop and
its snapshots), drawing (3D scene, markers, gizmos), camera_view (offscreen
camera picture), panel (buttons and figures), app (wiring and status), replay_viewer and
replay_subtasks (`teleop replay EP --serve`), viser_compat (the only user of viser's and
websockets' internals, checked by tests/test_viser_contract.py).
"""
