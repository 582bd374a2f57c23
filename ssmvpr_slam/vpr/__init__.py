"""VPR benchmark reporting for the application: plots of the loopclosure metrics.

Kept apart from ``loopclosure`` so the method package never needs matplotlib.
"""
