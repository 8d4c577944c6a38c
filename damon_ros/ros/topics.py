"""Every topic and service name of the damon_ros graph, in one place.

The names are the defaults of ``../shared/DESIGN.md``; nodes take them from here (and the
trajectory topic from a parameter), so a rename is one line and a remap (``-r FROM:=TO``)
works as in any ROS 2 package. The camera topics are the realsense2_camera driver's.
"""

JOINT_STATES = "/joint_states"
JOINT_COMMANDS = "/damon/joint_commands"
JOINT_TRAJECTORY = "/damon/joint_trajectory"
CONTROLLER_STATE = "/damon/controller_state"

GOAL_POSE = "goal_pose"
PLANNER_STATUS = "/damon/planner_status"
PLANNED_PATH = "/damon/planned_path"
GRAPH_MARKERS = "/damon/graph_markers"
PLAN_SERVICE = "~/plan"
STOP_SERVICE = "~/stop"

OBSTACLES = "/damon/obstacles"
COLOR_IMAGE = "/camera/camera/color/image_raw"
DEPTH_IMAGE = "/camera/camera/aligned_depth_to_color/image_raw"
CAMERA_INFO = "/camera/camera/color/camera_info"

SIM_OBSTACLES = "/damon/sim/obstacles"
"""Ground truth of the mock camera's scene (evaluation only)."""
SIM_CONTACT = "/damon/sim/contact"
SIM_LIMITS = "/damon/sim/limits"
