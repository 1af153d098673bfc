"""ROS 2 message definitions (ros2msg text, as rosbag2 writes them into MCAP
schemas) for the messages rotcal writes, and the schema names it reads:
sensor_msgs/msg/Imu and sensor_msgs/msg/JointState."""

IMU_SCHEMA = "sensor_msgs/msg/Imu"
JOINT_SCHEMA = "sensor_msgs/msg/JointState"

_SEP = "=" * 80

_HEADER = """builtin_interfaces/Time stamp
string frame_id"""

_TIME = """int32 sec
uint32 nanosec"""

_QUATERNION = """float64 x 0
float64 y 0
float64 z 0
float64 w 1"""

_VECTOR3 = """float64 x
float64 y
float64 z"""


def _with_deps(main: str, deps: list[tuple[str, str]]) -> str:
    return main + "".join(f"\n{_SEP}\nMSG: {name}\n{text}" for name, text in deps)


IMU = _with_deps(
    """std_msgs/Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance""",
    [
        ("std_msgs/Header", _HEADER),
        ("builtin_interfaces/Time", _TIME),
        ("geometry_msgs/Quaternion", _QUATERNION),
        ("geometry_msgs/Vector3", _VECTOR3),
    ],
)

JOINT_STATE = _with_deps(
    """std_msgs/Header header
string[] name
float64[] position
float64[] velocity
float64[] effort""",
    [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)],
)
