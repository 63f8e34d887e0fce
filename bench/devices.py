"""Device-to-command latency: how long an input waits before a control tick hands it on.

What is measured, in a 30 Hz control loop paced by wall time (as `teleop run`
paces people), calling each device's `poll()` once per tick:

- SpaceMouse: reports (combined layout, 125/s with jitter, like a Wireless
  model) are handed to the real reading thread through a stand-in HID handle;
  latency = from the moment a report is handed to the handle until `poll()`
  returns a Command reflecting it (or a newer report). Uses no hardware.
- Keyboard (only where Xvfb and xdotool exist): keys sent by xdotool to a
  private Xvfb display reach the real pynput listener; latency = from the
  listener callback for the key press until `poll()` returns the first
  Command moving because of it.

An input waits for the next tick and no longer: with no queueing the median is
about half a tick (16.7 ms at 30 Hz) and the maximum about one tick (33 ms).
`device_latency_max_ticks` above ~1.1 would mean an input sat out a tick.
"""

from __future__ import annotations

import os
import queue
import random
import select
import shutil
import subprocess
import threading
import time

import numpy as np

HZ = 30.0
DT = 1.0 / HZ


class _ReportHandle:
    """Stand-in HID handle: reports are queued with the time they were handed over."""

    def __init__(self) -> None:
        self.queue: queue.Queue = queue.Queue()

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        try:
            return list(self.queue.get(timeout=timeout_ms / 1000))
        except queue.Empty:
            return []

    def close(self) -> None:
        pass


def _spacemouse_latencies(seconds: float) -> list[float]:
    from devices.spacemouse import SpaceMouseDevice
    from devices.spacemouse_protocol import encode_combined

    handle = _ReportHandle()
    device = SpaceMouseDevice(lambda: handle, deadzone=0.0, pos_speed=1.0, stance="behind")
    device.start()
    sent: list[float] = []  # sent[i] = time report i (x = i + 1) was handed over
    stop = threading.Event()

    def send() -> None:
        rng = random.Random(0)
        while not stop.is_set() and len(sent) < 340:
            time.sleep(rng.uniform(0.004, 0.012))
            sent.append(time.monotonic())
            handle.queue.put(encode_combined(len(sent), 0, 0, 0, 0, 0))

    sender = threading.Thread(target=send, daemon=True)
    seen: list[tuple[float, int]] = []  # (poll return time, newest report index reflected)
    next_tick = time.monotonic()
    end = next_tick + seconds
    sender.start()
    try:
        while time.monotonic() < end:
            next_tick += DT
            time.sleep(max(0.0, next_tick - time.monotonic()))
            commands = device.poll(None, DT)
            returned = time.monotonic()
            if commands:
                # behind stance: HID +x -> world -y; raw x = report index + 1
                raw = -commands[0].translation[1] / DT * 350.0
                seen.append((returned, int(round(raw)) - 1))
    finally:
        stop.set()
        sender.join()
        device.close()
    latencies = []
    for i, t_sent in enumerate(sent):
        later = [t for t, newest in seen if newest >= i and t >= t_sent]
        if later:
            latencies.append(later[0] - t_sent)
    return latencies


def _start_xvfb() -> tuple[subprocess.Popen, str] | None:
    if not (shutil.which("Xvfb") and shutil.which("xdotool")):
        return None
    read_end, write_end = os.pipe()
    proc = subprocess.Popen(
        ["Xvfb", "-displayfd", str(write_end), "-nolisten", "tcp", "-noreset", "-screen", "0", "320x240x24"],
        pass_fds=(write_end,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(write_end)
    number = b""
    deadline = time.monotonic() + 15
    while not number.endswith(b"\n") and time.monotonic() < deadline:  # Xvfb writes "N\n" once it listens
        if not select.select([read_end], [], [], 0.5)[0]:
            continue
        chunk = os.read(read_end, 16)
        if not chunk:
            break
        number += chunk
    number = number.strip()
    os.close(read_end)
    if not number:
        proc.kill()
        proc.wait()
        return None
    return proc, f":{number.decode()}"


def _keyboard_latencies(presses: int) -> list[float]:
    started = _start_xvfb()
    if started is None:
        return []
    proc, display = started
    old = os.environ.get("DISPLAY")
    os.environ["DISPLAY"] = display
    env = {**os.environ, "DISPLAY": display}
    try:
        from devices.keyboard import KeyboardDevice

        device = KeyboardDevice(pos_speed=0.1)
        device.start()

        def press_keys() -> None:
            rng = random.Random(1)
            for _ in range(presses):
                time.sleep(rng.uniform(0.05, 0.12))
                subprocess.run(["xdotool", "keydown", "w"], env=env, check=True)
                time.sleep(rng.uniform(0.1, 0.15))
                subprocess.run(["xdotool", "keyup", "w"], env=env, check=True)

        presser = threading.Thread(target=press_keys, daemon=True)
        latencies: list[float] = []
        moving = False
        next_tick = time.monotonic()
        presser.start()
        while presser.is_alive():
            next_tick += DT
            time.sleep(max(0.0, next_tick - time.monotonic()))
            commands = device.poll(None, DT)
            returned = time.monotonic()
            now_moving = any(c.translation[0] > 0 for c in commands)
            if now_moving and not moving:
                latencies.append(returned - device.last_event_time)
            moving = now_moving
        device.close()
        listener = device._listener
        for _ in range(20):  # pynput's X11 listener notices stop() at the next key event
            if not listener.is_alive():
                break
            subprocess.run(["xdotool", "key", "Shift_L"], env=env, check=True)
            listener.join(0.1)
        return latencies
    finally:
        if old is None:
            os.environ.pop("DISPLAY", None)
        else:
            os.environ["DISPLAY"] = old
        proc.terminate()
        proc.wait()


def measure(quick: bool = False) -> dict[str, float]:
    mouse = _spacemouse_latencies(1.5 if quick else 4.0)
    keys = _keyboard_latencies(6 if quick else 20)
    both = mouse + keys
    out = {
        "device_latency_ms": round(float(np.median(both)) * 1000, 2),
        "device_latency_p95_ms": round(float(np.percentile(both, 95)) * 1000, 2),
        "device_latency_max_ms": round(float(np.max(both)) * 1000, 2),
        "device_latency_max_ticks": round(float(np.max(both)) / DT, 3),
        "spacemouse_latency_ms": round(float(np.median(mouse)) * 1000, 2),
    }
    if keys:
        out["keyboard_latency_ms"] = round(float(np.median(keys)) * 1000, 2)
    return out


if __name__ == "__main__":
    print(measure(quick=False))
