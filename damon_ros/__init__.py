"""damon_ros: the DAMON latent-manifold planner for the Franka Panda, as ROS 2 nodes."""

__version__ = "0.1.0"
