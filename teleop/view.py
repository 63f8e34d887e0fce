"""Transitional alias: the session view a device sees lives with the devices (devices/view.py)."""

from devices.view import SessionView

__all__ = ["SessionView"]
