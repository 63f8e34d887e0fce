"""The review page (`teleop review`): server (a stdlib HTTP server behind the shared gate) and the
page itself, review.html and review.js, over replay/review/."""
