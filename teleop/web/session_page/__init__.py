"""The session page (`teleop serve`): serve() opens the devices and runs WebApp, which wires the sim
thread (sim_thread), the 3D scene (drawing, body_poses), the camera picture (camera_view), the panel
(panel), and the page's own devices and keys (page_devices, page_keyboard) that arrive over the
input channel (teleop.web.shared.input_channel) from page_input.js and page_devices.js; the phone
page (phone.html) is served beside it."""
