"""The control tick and what runs it: IK, the controller, the session, the episode loop and its recorder."""
