// Gamepads (Gamepad API) and a SpaceMouse over WebHID, read in the operator's browser and sent on the
// page's input channel (`send`, given by the channel's script). The server validates every message and
// feeds devices/gamepad.py and devices/webhid.py; it treats a silent pad as released. `ui` names the panel's
// "Connect SpaceMouse" button as viser draws it: {button: CSS selector, connectSpaceMouse: its label}
// (teleop/web/session_page/page_devices.py, teleop/web/viser_internals/page_script.py).
(function (send, ui) {
  "use strict";
  if (window.__teleopPageDevices) return;
  const state = window.__teleopPageDevices = {gamepadStates: 0, hidReports: 0, hidDevice: null};

  // -- gamepad: the first connected pad, standard mapping; on change, and every 200 ms while connected ----
  let last = "", lastSent = 0, hadPad = false;
  function readPad() {
    const pads = navigator.getGamepads ? Array.from(navigator.getGamepads() || []) : [];
    const pad = pads.find((p) => p && p.connected && p.mapping === "standard") || pads.find((p) => p && p.connected);
    const now = performance.now();
    if (!pad) {
      if (hadPad) send({type: "gamepad", id: "", axes: [], buttons: [], connected: false});
      hadPad = false;
      return;
    }
    hadPad = true;
    const axes = Array.from(pad.axes).slice(0, 8).map((v) => Math.round(v * 1000) / 1000);
    const buttons = Array.from(pad.buttons).slice(0, 20).map((b) => Math.round((typeof b === "object" ? b.value || (b.pressed ? 1 : 0) : b) * 1000) / 1000);
    const key = JSON.stringify([axes, buttons]);
    if (key !== last || now - lastSent > 200) {
      send({type: "gamepad", id: String(pad.id || "").slice(0, 120), axes, buttons, connected: true});
      last = key;
      lastSent = now;
      state.gamepadStates += 1;
    }
  }
  setInterval(readPad, 16);
  window.addEventListener("blur", () => { if (hadPad) send({type: "gamepad", id: "", axes: [], buttons: [], connected: false}); last = ""; });

  // -- SpaceMouse over WebHID: the panel's "Connect SpaceMouse" button asks the browser (a user gesture) ----
  const FILTERS = [{vendorId: 0x256f}, {vendorId: 0x046d}];
  async function useDevice(device) {
    if (!device.opened) await device.open();
    state.hidDevice = device;
    send({type: "hid_connect", product: String(device.productName || "SpaceMouse").slice(0, 80)});
    device.addEventListener("inputreport", (e) => {
      const bytes = new Uint8Array(e.data.buffer, e.data.byteOffset, e.data.byteLength);
      send({type: "hid", report_id: e.reportId, data: Array.from(bytes.slice(0, 63))});
      state.hidReports += 1;
    });
  }
  if (navigator.hid) {
    navigator.hid.getDevices().then((devices) => { if (devices.length) useDevice(devices[0]).catch(() => {}); }).catch(() => {});
    navigator.hid.addEventListener && navigator.hid.addEventListener("disconnect", (e) => {
      if (e.device === state.hidDevice) { state.hidDevice = null; send({type: "hid_disconnect"}); }
    });
  }
  document.addEventListener("click", (e) => {  // viser's button: listened to here, so the click is the gesture
    const button = e.target && e.target.closest && e.target.closest(ui.button);
    if (!button || button.textContent.trim() !== ui.connectSpaceMouse) return;
    if (!navigator.hid) { alert("This browser has no WebHID: use Chrome or Edge"); return; }
    navigator.hid.requestDevice({filters: FILTERS})
      .then((devices) => devices.length ? useDevice(devices[0]) : null)
      .catch((err) => console.warn("WebHID:", err));
  }, true);
})
