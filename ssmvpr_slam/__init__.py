"""ssmvpr-slam: streaming SSM-VPR loop closures with a GTSAM back end."""

__version__ = "0.1.0"
