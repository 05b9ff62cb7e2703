"""A synthetic Azure Kinect rig: cameras, ray-cast rendering, sensor noise and whole captures."""
