"""From a sentence to a demonstration: a camera finds the objects (perceive), a planner turns the words into
the script engine's atomic actions (grammar, planner, plan_url). docs/instruct.md tells the story."""
