"""Training: one loop for every model (`loop.py`), checkpoints, distributed setup, the pose and
detector tasks that plug into the loop."""
