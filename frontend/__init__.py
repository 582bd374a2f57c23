"""Logged traverses in, odometry out, keyframes, and simulated traverses."""
