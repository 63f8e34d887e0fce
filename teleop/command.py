"""Transitional alias: the Command type lives with the devices (devices/command.py)."""

from devices.command import EVENTS, Command, Event, Frame, GripperCommand

__all__ = ["EVENTS", "Command", "Event", "Frame", "GripperCommand"]
