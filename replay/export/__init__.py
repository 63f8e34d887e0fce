"""Recorded episodes into LeRobot datasets: frames, rendering stream, image statistics, parallel shards."""
