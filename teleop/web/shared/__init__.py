"""What two pages or more use (a page's room imports no other page's room): access (token, loopback
Host rule, wrong-token throttle; plain Python, no viser), net (host and port checks, URLs), stdlib_http
(the stdlib servers' deadline, JSON bodies, files with Range, the stylesheet static/teleop.css),
input_channel, input_messages and page_input.js (the 3D pages' websocket, its messages and its script),
camera_markers (the camera's start and the end-effector markers), view_quality (a lighter view for
software WebGL), loop_thread and cpu_pressure (background loops that yield under load)."""
