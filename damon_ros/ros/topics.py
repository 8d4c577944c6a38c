"""Every topic and service name of the damon_ros graph, in one place.

The names are the defaults of ``../shared/DESIGN.md``; nodes take them from here (and the
trajectory and joint-state topics from parameters), so a rename is one line. Every name is
*relative*: it resolves in the node's namespace (``ros2 run ... --ros-args -r
__ns:=/left``, franka_ros2's ``namespace:=`` launch argument) and a remap (``-r FROM:=TO``)
works as in any ROS 2 package; in the root namespace ``joint_states`` is ``/joint_states``.
The camera topics are the realsense2_camera driver's (``camera/camera/...``).
"""

JOINT_STATES = "joint_states"
JOINT_COMMANDS = "damon/joint_commands"
JOINT_TRAJECTORY = "damon/joint_trajectory"
CONTROLLER_STATE = "damon/controller_state"

GOAL_POSE = "goal_pose"
PLANNER_STATUS = "damon/planner_status"
PLANNED_PATH = "damon/planned_path"
GRAPH_MARKERS = "damon/graph_markers"
PLAN_SERVICE = "~/plan"
STOP_SERVICE = "~/stop"

OBSTACLES = "damon/obstacles"
CAMERA_PREFIX = "camera/camera"
"""realsense2_camera's ``<camera_namespace>/<camera_name>``; each camera has its own."""


def camera_topics(prefix: str = CAMERA_PREFIX) -> tuple[str, str, str]:
    """Colour, aligned depth and camera_info topics of the camera publishing under
    ``prefix`` (one mock_camera or RealSense driver per camera, each with its own prefix)."""
    prefix = prefix.rstrip("/")  # a leading "/" makes the topics absolute, as in ROS
    if not prefix.strip("/"):
        raise ValueError("a camera topic prefix must not be empty")
    return (f"{prefix}/color/image_raw", f"{prefix}/aligned_depth_to_color/image_raw",
            f"{prefix}/color/camera_info")


COLOR_IMAGE, DEPTH_IMAGE, CAMERA_INFO = camera_topics()

SIM_OBSTACLES = "damon/sim/obstacles"
"""Ground truth of the mock camera's scene (evaluation only)."""
SIM_CONTACT = "damon/sim/contact"
SIM_LIMITS = "damon/sim/limits"
