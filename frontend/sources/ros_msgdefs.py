"""ROS 2 message definitions (ros2msg text) for the schemas the writer registers.

The text follows rosbag2's convention: the top-level definition, then each dependency
after a line of ``=`` and ``MSG: pkg/Type``. Names are fully qualified so any ros2msg
parser (mcap_ros2, Foxglove) resolves them without a package context.
"""

from __future__ import annotations

_SEPARATOR = "=" * 80


def _compose(top: str, *dependencies: tuple[str, str]) -> str:
    parts = [top.strip()]
    for name, body in dependencies:
        parts.append(f"{_SEPARATOR}\nMSG: {name}\n{body.strip()}")
    return "\n".join(parts) + "\n"


_TIME = ("builtin_interfaces/Time", "int32 sec\nuint32 nanosec")
_HEADER = ("std_msgs/Header", "builtin_interfaces/Time stamp\nstring frame_id")
_POINT = ("geometry_msgs/Point", "float64 x\nfloat64 y\nfloat64 z")
_QUATERNION = (
    "geometry_msgs/Quaternion",
    "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
)
_VECTOR3 = ("geometry_msgs/Vector3", "float64 x\nfloat64 y\nfloat64 z")
_POSE = (
    "geometry_msgs/Pose",
    "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation",
)
_TWIST = ("geometry_msgs/Twist", "geometry_msgs/Vector3 linear\ngeometry_msgs/Vector3 angular")
_POSE_COV = ("geometry_msgs/PoseWithCovariance", "geometry_msgs/Pose pose\nfloat64[36] covariance")
_TWIST_COV = (
    "geometry_msgs/TwistWithCovariance",
    "geometry_msgs/Twist twist\nfloat64[36] covariance",
)
_POINT_FIELD = (
    "sensor_msgs/PointField",
    """
uint8 INT8    = 1
uint8 UINT8   = 2
uint8 INT16   = 3
uint8 UINT16  = 4
uint8 INT32   = 5
uint8 UINT32  = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8  datatype
uint32 count
""",
)

_COLOR = ("std_msgs/ColorRGBA", "float32 r\nfloat32 g\nfloat32 b\nfloat32 a")
_DURATION = ("builtin_interfaces/Duration", "int32 sec\nuint32 nanosec")
_POSE_STAMPED = ("geometry_msgs/PoseStamped", "std_msgs/Header header\ngeometry_msgs/Pose pose")
_COMPRESSED_IMAGE = ("sensor_msgs/CompressedImage", "std_msgs/Header header\nstring format\nuint8[] data")
_ROI = (
    "sensor_msgs/RegionOfInterest",
    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify",
)
_UV = ("visualization_msgs/UVCoordinate", "float32 u\nfloat32 v")
_MESH_FILE = ("visualization_msgs/MeshFile", "string filename\nuint8[] data")
_MARKER = (
    "visualization_msgs/Marker",
    """
int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11
int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3
std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked
geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors
string texture_resource
sensor_msgs/CompressedImage texture
visualization_msgs/UVCoordinate[] uv_coordinates
string text
string mesh_resource
visualization_msgs/MeshFile mesh_file
bool mesh_use_embedded_materials
""",
)

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
PATH = "nav_msgs/msg/Path"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

MSGDEFS: dict[str, str] = {
    IMAGE: _compose(
        """
std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
""",
        _HEADER,
        _TIME,
    ),
    COMPRESSED_IMAGE: _compose("std_msgs/Header header\nstring format\nuint8[] data", _HEADER, _TIME),
    CAMERA_INFO: _compose(
        """
std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
uint32 binning_x
uint32 binning_y
sensor_msgs/RegionOfInterest roi
""",
        _HEADER,
        _TIME,
        _ROI,
    ),
    POINT_CLOUD2: _compose(
        """
std_msgs/Header header
uint32 height
uint32 width
sensor_msgs/PointField[] fields
bool    is_bigendian
uint32  point_step
uint32  row_step
uint8[] data
bool is_dense
""",
        _HEADER,
        _TIME,
        _POINT_FIELD,
    ),
    ODOMETRY: _compose(
        """
std_msgs/Header header
string child_frame_id
geometry_msgs/PoseWithCovariance pose
geometry_msgs/TwistWithCovariance twist
""",
        _HEADER,
        _TIME,
        _POSE_COV,
        _POSE,
        _POINT,
        _QUATERNION,
        _TWIST_COV,
        _TWIST,
        _VECTOR3,
    ),
    POSE_STAMPED: _compose(
        "std_msgs/Header header\ngeometry_msgs/Pose pose",
        _HEADER,
        _TIME,
        _POSE,
        _POINT,
        _QUATERNION,
    ),
    PATH: _compose(
        "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses",
        _HEADER,
        _TIME,
        _POSE_STAMPED,
        _POSE,
        _POINT,
        _QUATERNION,
    ),
    MARKER_ARRAY: _compose(
        "visualization_msgs/Marker[] markers",
        _MARKER,
        _HEADER,
        _TIME,
        _POSE,
        _POINT,
        _QUATERNION,
        _VECTOR3,
        _COLOR,
        _DURATION,
        _COMPRESSED_IMAGE,
        _UV,
        _MESH_FILE,
    ),
}


def normalise_type(name: str) -> str:
    """``pkg/msg/Type`` for both ``pkg/Type`` and ``pkg/msg/Type`` spellings."""
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[-1]}" if len(parts) == 2 else name
