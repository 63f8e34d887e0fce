"""The browser pages, one sub-package (room) each, and what they share.

- session_page/: `teleop serve` (serve, WebApp): the real-time sim thread, the 3D scene drawn on
  viser, the camera picture, the panel, the page's keys and devices, the phone page; their scripts
  (page_devices.js, phone.html).
- replay_page/: `teleop replay EP --serve`: the replay viewer and its Subtasks panel.
- review_page/: `teleop review`: the review page (a stdlib HTTP server), review.html and review.js.
- shared/: what two pages or more use (no page imports another page's room): the access gate (token,
  loopback Host rule, throttle; plain Python), host and port checks, the stdlib HTTP server's parts,
  the stylesheet, the input channel with its messages and script (page_input.js), the camera's start
  and the markers, the view quality for software WebGL, the loop thread and CPU pressure.
- viser_internals/: the only code that uses viser's, mjviser's or websockets' private names
  (tests/test_architecture.py checks it; tests/test_viser_contract.py checks them against the releases),
  and viser's start behind the gate (guarded_start).
"""
