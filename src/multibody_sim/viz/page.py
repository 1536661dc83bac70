"""The viewer page: meshcat's viewer plus our handlers, as a live page (WebSocket) or one self-contained file.

Both pages expose `window.multibodySim` for people and tests: `loaded` (every command applied), `frame` and
`time` (the last frame marker), `received` (page clock and time of every frame marker), `errors`, `seek(t)`
(pause the recorded animation at time t [s]), `duration` and `rendered()` (a promise resolved once a frame has
been drawn since the call).
"""

from __future__ import annotations

import base64
import html
import struct
import zlib

# Our side of the page. Commands apply strictly in order: the export decodes them synchronously one after the
# other (meshcat's own export hands each to fetch(), whose promises resolve in any order, so a page could show
# links stuck at their start pose).
_SCRIPT = r"""
(function () {
  "use strict";
  const pane = document.getElementById("meshcat-pane");
  const viewer = new MeshCat.Viewer(pane);
  window.viewer = viewer;
  // received: [page clock (s), frame time (s)] of every frame marker, for whoever checks the pacing.
  const state = {loaded: false, frame: -1, time: null, errors: [], duration: 0, received: []};
  window.multibodySim = state;

  function setCamera(cmd) {
    // meshcat's world is z-up; three.js's is y-up: (x, y, z) -> (x, z, -y). The camera's parents rotate by
    // -90 deg then +90 deg about x, so its local coordinates are three.js world coordinates.
    const p = cmd.position, t = cmd.target, camera = viewer.camera;
    viewer.controls.target.set(t[0], t[2], -t[1]);
    camera.position.set(p[0], p[2], -p[1]);
    camera.near = cmd.near;
    camera.far = cmd.far;
    camera.updateProjectionMatrix();
    viewer.controls.update();
    viewer.set_dirty();
  }

  function showPlot(cmd) {
    const panel = document.getElementById("plot-panel");
    const image = document.getElementById("plot-image");
    image.src = URL.createObjectURL(new Blob([cmd.png], {type: "image/png"}));
    state.plotCursor = cmd.cursor || null;
    panel.style.display = "flex";
    viewer.set_3d_pane_size();
  }

  // The time the robot shows: the recorded animation's, else the last streamed frame's.
  function shownTime() {
    const actions = viewer.animator.actions;
    if (actions.length > 0) return state.animationStart + actions.reduce((t, a) => Math.max(t, a.time), 0);
    return state.time;
  }
  state.animationStart = 0;
  state.shownTime = shownTime;

  // A vertical line over the plot at that time, every frame.
  function moveCursor() {
    requestAnimationFrame(moveCursor);
    const line = document.getElementById("plot-cursor");
    const c = state.plotCursor, t = shownTime();
    if (!c || t === null || t === undefined || c.t1 <= c.t0) {
      line.style.display = "none";
      return;
    }
    const image = document.getElementById("plot-image").getBoundingClientRect();
    const panel = document.getElementById("plot-panel").getBoundingClientRect();
    const x = c.left + (t - c.t0) / (c.t1 - c.t0) * (c.right - c.left);
    line.style.display = "block";
    line.style.left = (image.left - panel.left + x * image.width) + "px";
    line.style.top = (image.top - panel.top + c.top * image.height) + "px";
    line.style.height = ((c.bottom - c.top) * image.height) + "px";
  }
  requestAnimationFrame(moveCursor);

  function seek(time) {
    const animator = viewer.animator;
    if (animator.actions.length === 0) return;
    const t = Math.max(0, Math.min(time, animator.duration - 1e-6));
    animator.pause();
    for (const action of animator.actions) {
      action.enabled = true;
      action.paused = false;
      action.play();
    }
    animator.seek(t);
    animator.display_progress(t);
    viewer.set_dirty();
  }
  state.seek = seek;
  state.rendered = function () {
    viewer.set_dirty();
    return new Promise((resolve) => requestAnimationFrame(() => requestAnimationFrame(() => resolve(true))));
  };

  const meshcatHandle = viewer.handle_command.bind(viewer);
  viewer.handle_command = function (cmd) {
    try {
      if (cmd.type === "multibody_sim_camera") {
        setCamera(cmd);
      } else if (cmd.type === "multibody_sim_plot") {
        showPlot(cmd);
      } else if (cmd.type === "multibody_sim_frame") {
        state.frame = cmd.index;
        state.time = cmd.time;
        if (state.received.length < 100000) state.received.push([performance.now() / 1000, cmd.time]);
      } else if (cmd.type === "multibody_sim_ready") {
        state.loaded = true;
        document.documentElement.dataset.loaded = "true";
        // Tell a live server the scene is drawn: it starts a playback only then.
        if (viewer.connection && viewer.connection.readyState === WebSocket.OPEN) {
          viewer.connection.send(JSON.stringify({type: "multibody_sim_loaded"}));
        }
      } else {
        meshcatHandle(cmd);
        if (cmd.type === "set_animation") {
          state.duration = viewer.animator.duration;
          const options = cmd.options || {};
          state.animationStart = options.multibody_sim_start || 0;
          if (options.multibody_sim_speed !== undefined) viewer.animator.mixer.timeScale = options.multibody_sim_speed;
          if (options.multibody_sim_seek !== undefined) seek(options.multibody_sim_seek);
        }
      }
    } catch (error) {
      state.errors.push(String(error && error.stack || error));
      console.error(error);
    }
    viewer.set_dirty();
  };
  __SOURCE__
})();
"""

_EMBEDDED_SOURCE = r"""
  // The commands: zlib-compressed, each one a little-endian uint32 length then its msgpack bytes.
  async function load() {
    const status = document.getElementById("status");
    status.textContent = "loading...";
    const text = atob(document.getElementById("multibody-sim-commands").textContent.trim());
    const packed = new Uint8Array(text.length);
    for (let i = 0; i < text.length; i++) packed[i] = text.charCodeAt(i);
    const stream = new Blob([packed]).stream().pipeThrough(new DecompressionStream("deflate"));
    const bytes = new Uint8Array(await new Response(stream).arrayBuffer());
    const view = new DataView(bytes.buffer);
    for (let offset = 0; offset < bytes.length;) {
      const size = view.getUint32(offset, true);
      offset += 4;
      viewer.handle_command_bytearray(bytes.slice(offset, offset + size));
      offset += size;
    }
    status.textContent = "";
    const hash = /[#&]t=([0-9.eE+-]+)/.exec(location.hash);
    if (hash) seek(parseFloat(hash[1]));
  }
  load().catch(function (error) {
    state.errors.push(String(error && error.stack || error));
    document.getElementById("status").textContent = "cannot load the recording: " + error;
  });
"""

_LIVE_SOURCE = r"""
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  viewer.connect(scheme + "//" + location.host + "/ws");
  viewer.connection.onclose = function () {
    document.getElementById("status").textContent = "disconnected from the simulation server";
  };
"""

_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
  html, body {{ margin: 0; height: 100%; overflow: hidden; font-family: sans-serif; }}
  #layout {{ display: flex; width: 100vw; height: 100vh; }}
  #viewer-wrap {{ position: relative; flex: 1 1 auto; min-width: 0; }}
  #meshcat-pane {{ width: 100%; height: 100vh; overflow: hidden; }}
  #plot-panel {{ display: none; flex: 0 0 42%; align-items: center; justify-content: center; background: #fff;
                border-left: 1px solid #ccc; }}
  #plot-panel {{ position: relative; }}
  #plot-image {{ max-width: 100%; max-height: 100%; }}
  #plot-cursor {{ display: none; position: absolute; width: 2px; margin-left: -1px; background: rgba(200, 0, 0, 0.6);
                 pointer-events: none; }}
  #status {{ position: absolute; left: 8px; bottom: 6px; color: #fff; font-size: 12px; }}
</style>
</head>
<body>
<div id="layout">
  <div id="viewer-wrap"><div id="meshcat-pane"></div><div id="status"></div></div>
  <aside id="plot-panel"><img id="plot-image" alt="energy and joint positions against time">
    <div id="plot-cursor"></div></aside>
</div>
{viewer_js}
{data}
<script>
{script}
</script>
</body>
</html>
"""


def live_page(title: str) -> str:
    """The page the live server serves: meshcat's viewer from /main.min.js, commands over /ws."""
    script = _SCRIPT.replace("__SOURCE__", _LIVE_SOURCE)
    return _PAGE.format(
        title=html.escape(title), viewer_js='<script src="main.min.js"></script>', data="", script=script
    )


def standalone_page(title: str, viewer_js: str, commands: list[bytes]) -> str:
    """One self-contained page: the viewer's JavaScript inline and every command (msgpack bytes) embedded.

    Raises:
        ValueError: the viewer's JavaScript contains "</script", which would end the inline script early.
    """
    if "</script" in viewer_js.lower():
        raise ValueError("the meshcat viewer JavaScript contains '</script' and cannot be inlined")
    packed = b"".join(struct.pack("<I", len(c)) + c for c in commands)
    encoded = base64.b64encode(zlib.compress(packed, 6)).decode("ascii")  # base64 never contains "</"
    data = f'<script type="text/plain" id="multibody-sim-commands">{encoded}</script>'
    script = _SCRIPT.replace("__SOURCE__", _EMBEDDED_SOURCE)
    return _PAGE.format(
        title=html.escape(title), viewer_js=f"<script>\n{viewer_js}\n</script>", data=data, script=script
    )
