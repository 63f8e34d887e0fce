"""The XR page (`/xr` on a session's server): a WebXR page that draws the scene itself and drives the arms
from a headset's controllers or hands (docs/xr.md)."""
