"""Pure numerics and geometry: nothing in this package may import ROS."""
