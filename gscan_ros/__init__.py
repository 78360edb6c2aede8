"""gscan_ros: grounded command following in gSCAN with compositional networks (Kuo et al. 2021)."""

__version__ = "0.1.0"
