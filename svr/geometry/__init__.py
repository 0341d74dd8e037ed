"""SE(3) and SO(3) geometry for poses, batched over any leading dimensions.

See :mod:`svr.geometry.so3` and :mod:`svr.geometry.se3` for the conventions.
"""

from svr.geometry.conversions import (
    ANCHOR_HALF_SIZE_MM,
    anchor_points_to_pose,
    pose_to_anchor_points,
    pose_to_quat_translation,
    pose_to_rotation_6d_translation,
    quat_translation_to_pose,
    rotation_6d_translation_to_pose,
)
from svr.geometry.rigid_fit import RigidFitError, weighted_rigid_fit
from svr.geometry.se3 import (
    se3_compose,
    se3_error,
    se3_group_exp,
    se3_group_log,
    se3_inverse,
    se3_to_vector,
    vector_to_se3,
)
from svr.geometry.so3 import (
    euler_to_matrix,
    hat,
    matrix_to_euler,
    matrix_to_quat,
    matrix_to_rotation_6d,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    quat_to_rotvec,
    regularize_rotvec,
    rotation_6d_to_matrix,
    rotation_angle,
    rotvec_to_quat,
    so3_exp,
    so3_left_jacobian,
    so3_left_jacobian_inverse,
    so3_log,
)

__all__ = [
    "ANCHOR_HALF_SIZE_MM",
    "RigidFitError",
    "anchor_points_to_pose",
    "euler_to_matrix",
    "hat",
    "matrix_to_euler",
    "matrix_to_quat",
    "matrix_to_rotation_6d",
    "pose_to_anchor_points",
    "pose_to_quat_translation",
    "pose_to_rotation_6d_translation",
    "quat_multiply",
    "quat_rotate",
    "quat_to_matrix",
    "quat_to_rotvec",
    "quat_translation_to_pose",
    "regularize_rotvec",
    "rotation_6d_to_matrix",
    "rotation_6d_translation_to_pose",
    "rotation_angle",
    "rotvec_to_quat",
    "se3_compose",
    "se3_error",
    "se3_group_exp",
    "se3_group_log",
    "se3_inverse",
    "se3_to_vector",
    "so3_exp",
    "so3_left_jacobian",
    "so3_left_jacobian_inverse",
    "so3_log",
    "vector_to_se3",
    "weighted_rigid_fit",
]
