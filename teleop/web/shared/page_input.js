// Keys typed in the teleop page, sent to the server's input channel.
//
// viser runs this with `new Function(source)()` (RunJavascriptMessage), once per
// connection of its own socket, so again after a reconnect; the server prepends
// `const CONFIG = {path, keys, client}` (teleop/web/session_page/page_keyboard.py).
// The first run installs the listeners; later runs only pass the new CONFIG on.
//
// Only bound keys are caught, in the capture phase on window, so viser's own
// keyboard camera (w/a/s/d fly it) never sees them; keys with Ctrl/Alt/Meta and
// keys typed into form fields are left alone. A held key is sent once (autorepeat
// is ignored) and its release is sent under the name it was pressed with. When
// the page loses focus or is hidden every held key is released (and the server
// lets go by itself when this socket closes or stops answering its pings).
//
// A lost server is hard to miss: when this socket closes (the server stopped, the network went away) a
// banner across the top of the page says "disconnected from the server: reconnecting..." (viser alone only
// greys its panel); it goes once this socket is open again and viser has reconnected too (viser then sends
// the whole scene and panel again, and runs this script again: `configure`).
(() => {
  const api = window.__teleopInput;
  if (api) {
    api.configure(CONFIG);
    return;
  }
  let config = CONFIG;
  let keys = new Set(config.keys);
  let socket = null;
  let retry = null;
  let closing = false;
  const held = new Map(); // KeyboardEvent.code -> the key sent down
  let lost = false; // the socket closed: the banner is up until this socket and viser's are back
  let viserBack = true; // viser ran this script since the loss (it does on every connection of its own)
  let banner = null;

  const showBanner = (show) => {
    if (show && banner === null) {
      banner = document.createElement("div");
      banner.id = "teleop-disconnected";
      banner.setAttribute("role", "alert");
      banner.textContent = "disconnected from the server: reconnecting…";
      // Inline style: this page is viser's and has no stylesheet of ours.
      banner.style.cssText = "position:fixed;top:0;left:0;right:0;z-index:100000;margin:0;padding:10px 12px;"
        + "background:#b3261e;color:#fff;font:600 15px system-ui,sans-serif;text-align:center;"
        + "box-shadow:0 2px 8px rgba(0,0,0,.5);pointer-events:none";
    }
    if (banner === null) return;
    if (show && !banner.isConnected) document.body.appendChild(banner);
    if (!show && banner.isConnected) banner.remove();
    document.documentElement.dataset.teleopConnection = show ? "lost" : "ok";
  };
  const updateBanner = () => {
    if (lost && socket !== null && socket.readyState === WebSocket.OPEN && viserBack) lost = false;
    showBanner(lost && !closing);
  };

  const send = (message) => {
    if (socket !== null && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
  };
  // Whether this browser draws WebGL on the CPU (no GPU, or acceleration off), as the script first in the
  // page found out (teleop/web/shared/view_quality.py): the server then gives this page a view a CPU draws quickly.
  const isSoftwareGl = () => window.__teleopSoftwareGl === true;
  const hello = () => {
    send({ type: "hello", client: config.client, agent: navigator.userAgent.slice(0, 200) });
    send({ type: "view", client: config.client, software_gl: isSoftwareGl() });
  };

  const url = () => {
    const scheme = window.location.protocol === "https:" ? "wss://" : "ws://";
    const token = new URLSearchParams(window.location.search).get("token");
    // The cookie set with the page carries the token too; the query is for browsers without cookies.
    return scheme + window.location.host + config.path + (token ? "?token=" + encodeURIComponent(token) : "");
  };

  const connect = () => {
    retry = null;
    if (closing) return;
    const ws = new WebSocket(url());
    socket = ws;
    ws.onopen = () => {
      hello();
      updateBanner();
    };
    ws.onclose = () => {
      if (socket !== ws) return;
      socket = null;
      held.clear(); // the server let go of this page's keys when the socket closed
      if (!closing) {
        lost = true;
        viserBack = false;
        updateBanner();
      }
      if (!closing && retry === null) retry = setTimeout(connect, 1000);
    };
  };

  const releaseAll = (why) => {
    held.clear();
    send({ type: "release_all", why });
  };

  const isFormField = (target) => {
    if (!(target instanceof HTMLElement)) return false;
    if (target.isContentEditable) return true;
    const tag = target.tagName;
    if (tag === "TEXTAREA" || tag === "SELECT") return true;
    if (tag !== "INPUT") return false;
    const kind = (target.getAttribute("type") || "text").toLowerCase();
    return !["button", "checkbox", "radio", "range", "color", "submit", "reset"].includes(kind);
  };
  const bound = (event) => keys.has(event.key);

  const onKeyDown = (event) => {
    if (!bound(event) || isFormField(event.target)) return;
    if (event.ctrlKey || event.altKey || event.metaKey) return; // Ctrl+W and friends belong to the browser
    event.preventDefault(); // no scrolling (space), focus moves (tab) or button clicks (enter, space)
    event.stopPropagation(); // no camera flight on w/a/s/d
    const code = event.code || event.key;
    if (event.repeat || held.has(code)) return;
    held.set(code, event.key);
    send({ type: "key", key: event.key, down: true });
  };
  const onKeyUp = (event) => {
    const code = event.code || event.key;
    const key = held.get(code);
    if (key === undefined) {
      if (bound(event) && !isFormField(event.target)) {
        event.preventDefault();
        event.stopPropagation();
      }
      return;
    }
    held.delete(code);
    event.preventDefault();
    event.stopPropagation();
    send({ type: "key", key, down: false });
  };

  window.addEventListener("keydown", onKeyDown, true);
  window.addEventListener("keyup", onKeyUp, true);
  window.addEventListener("blur", () => releaseAll("blur"));
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "hidden") releaseAll("hidden");
  });
  window.addEventListener("pagehide", () => {
    releaseAll("pagehide");
    closing = true;
    if (socket !== null) socket.close();
  });
  window.addEventListener("pageshow", (event) => {
    if (!event.persisted) return; // back from the back-forward cache: talk again
    closing = false;
    if (socket === null && retry === null) connect();
  });

  window.__teleopInput = {
    configure(next) {
      config = next;
      keys = new Set(config.keys);
      viserBack = true;
      if (socket === null && retry === null) connect();
      else hello();
      updateBanner();
    },
    connected: () => socket !== null && socket.readyState === WebSocket.OPEN,
    disconnected: () => lost,
    held: () => Array.from(held.values()),
    sendRaw: (text) => {
      // For tests and debugging: a message as given, valid or not (the server must cope).
      if (socket !== null && socket.readyState === WebSocket.OPEN) socket.send(text);
    },
  };
  connect();
})();
