"""Perception: RealSense colour + depth frames -> tracked obstacles in the robot base frame.

No ROS here (the tracker node adapts it). Read in pipeline order: ``camera`` (pinhole model
and hand-eye calibration), ``tracker_config`` (the settings), ``segmentation`` (coloured
blobs), ``shape_fit`` (conservative bounds), ``velocity`` (moving-window velocity fit) and
``tracking`` (detections of a frame, tracks with stable ids).
"""
