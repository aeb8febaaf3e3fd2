"""Small rigid-transform helpers shared by every stage.

All transforms are 4×4 float64 `T_<to>_<from>`; rotations 3×3 float64; quaternions (w, x, y, z) as in Scan2CAD.
"""

from __future__ import annotations

import numpy as np


def _rotation():
    """SciPy's Rotation, imported on first use: this module is imported by every process, a server's parent among
    them, which never turns a quaternion, and scipy.spatial costs it 0.4 s of its start."""
    from scipy.spatial.transform import Rotation

    return Rotation


def make_T(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4×4 float64 from a 3×3 rotation and a 3-vector translation (either may be omitted)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def make_Ts(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(h, 3, 3) rotations and (h, 3) translations -> (h, 4, 4) poses (`make_T` of many)."""
    T = np.tile(np.eye(4), (len(R), 1, 1))
    T[:, :3, :3], T[:, :3, 3] = R, t
    return T


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """T (4, 4), finite: a rotation (orthonormal, det +1, within `tol`) and a translation, bottom row 0 0 0 1."""
    R = T[:3, :3]
    if np.abs(R).max() > 1.0 + tol:  # a rotation's entries lie in [-1, 1]; checked first, as R @ R.T may overflow
        return False
    return bool(np.allclose(R @ R.T, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1.0) < tol
                and np.allclose(T[3], [0, 0, 0, 1], atol=1e-9))


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform, without a general matrix inverse."""
    R = T[:3, :3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ T[:3, 3]
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """points : (n, 3) float in frame `from` -> (n, 3) float64 in frame `to`."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def quat_wxyz_to_R(q: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternion (any norm) -> 3×3 rotation."""
    w, x, y, z = np.asarray(q, dtype=float)
    return _rotation().from_quat([x, y, z, w]).as_matrix()


def R_to_quat_wxyz(R: np.ndarray) -> np.ndarray:
    """3×3 rotation -> (w, x, y, z) unit quaternion with w ≥ 0 (of q and −q, the canonical one: a client comparing
    answers' quaternions component by component sees one rotation as one quaternion)."""
    x, y, z, w = _rotation().from_matrix(R).as_quat(canonical=True)
    return np.array([w, x, y, z])


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix in degrees, robust to round-off.

    atan2(sin, cos) rather than arccos of the trace: near 0° arccos turns a matrix that is 5e-5 off orthonormal
    (7-Scenes stores its poses so) into a 1° "error"; the skew part carries the angle, the trace only its sign.
    """
    R = np.asarray(R, dtype=float)
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    c = 0.5 * (np.trace(R) - 1.0)
    return float(np.degrees(np.arctan2(s, c)))


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to a 3×3 matrix in the Frobenius norm (SVD projection onto SO(3))."""
    U, _, Vt = np.linalg.svd(np.asarray(M, dtype=float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(translation error in metres, rotation error in degrees) between two poses of the same frames."""
    dT = invert_T(T_true) @ T_est
    return float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])), rotation_angle_deg(dT[:3, :3])


def kabsch_many(source: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid fits (Kabsch, paper eq. 9) of one source (n, 3) onto many targets (m, n, 3) in one
    batched SVD: R (m, 3, 3), t (m, 3) with target ≈ R @ source + t; n >= 3 for a unique answer."""
    P = np.asarray(source, dtype=float)
    Q = np.asarray(targets, dtype=float)
    mp, mq = P.mean(axis=0), Q.mean(axis=1)
    H = np.einsum("ki,mkj->mij", P - mp, Q - mq[:, None]) / len(P)
    U, _, Vt = np.linalg.svd(H)
    V, Ut = np.swapaxes(Vt, 1, 2), np.swapaxes(U, 1, 2)
    d = np.sign(np.linalg.det(V @ Ut))
    R = V @ (np.concatenate([np.ones((len(d), 2)), d[:, None]], axis=1)[:, :, None] * Ut)
    return R, mq - np.einsum("mij,j->mi", R, mp)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Smallest rotation taking unit vector a onto unit vector b."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(a @ b)
    if np.linalg.norm(v) < 1e-12:
        if c > 0:
            return np.eye(3)
        # 180°: any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        return _rotation().from_rotvec(np.pi * axis / np.linalg.norm(axis)).as_matrix()
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * (1.0 / (1.0 + c))
