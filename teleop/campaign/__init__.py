"""Collection campaigns: many operators at once, each in a browser session of their own.

`teleop campaign FILE` reads the campaign file (file.py), serves a lobby (lobby.py)
where operators join, starts one `teleop serve`-like process per operator
(sessions.py, operator_session.py) and counts episodes and hands out seeds from
what is on disk under the campaign's `out/` folder (ledger.py), so counts and seeds
survive restarts. docs/campaigns.md describes it for users.
"""
