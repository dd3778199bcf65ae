"""Pinhole camera with OpenCV's distortion coefficients.

The coefficient vector is always OpenCV's 12-element order (k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4).
The seed paper's model (radial k1..k3, tangential t1 t2, thin prism p) is the subset with k4..k6 = 0,
p1 = t1, p2 = t2, s1 = p_x, s3 = p_y and s2 = s4 = 0 (its equations 1-4 written out match OpenCV's).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from lapreco_hil.errors import CalibrationError

N_DIST = 12
FOV_KINDS = ("circle", "ellipse", "mask")


@dataclass(frozen=True)
class FieldOfView:
    """The part of the distorted image the scope's optics light (outside it: black, no features). A circle
    (centre, radius ``r``), an ellipse (centre, semi-axes ``a`` along ``angle_deg`` from the image x axis
    towards y, and ``b``), or a mask image (``mask_file``: non-zero = inside, read on first use and kept).
    Build one with :meth:`circle`, :meth:`ellipse` or :meth:`mask`; consumers call ``CameraModel.fov_mask``."""

    kind: str
    cx: float = 0.0
    cy: float = 0.0
    r: float = 0.0
    a: float = 0.0
    b: float = 0.0
    angle_deg: float = 0.0
    mask_file: str = ""
    # the mask file's pixels once read (a mask camera is compared and hashed by its file name, not its pixels)
    _loaded: dict = field(default_factory=dict, compare=False, hash=False, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in FOV_KINDS:
            raise ValueError(f"field of view kind '{self.kind}': use one of {', '.join(FOV_KINDS)}")

    @staticmethod
    def circle(cx: float, cy: float, r: float) -> "FieldOfView":
        return FieldOfView("circle", float(cx), float(cy), r=float(r))

    @staticmethod
    def ellipse(cx: float, cy: float, a: float, b: float, angle_deg: float = 0.0) -> "FieldOfView":
        return FieldOfView("ellipse", float(cx), float(cy), a=float(a), b=float(b), angle_deg=float(angle_deg))

    @staticmethod
    def mask(path, pixels: np.ndarray | None = None) -> "FieldOfView":
        """A mask image file; ``pixels`` (bool, H x W), when the caller has already read and checked it."""
        fov = FieldOfView("mask", mask_file=str(path))
        if pixels is not None:
            fov._loaded["inside"] = np.asarray(pixels, bool)
        return fov

    def inside(self) -> np.ndarray:
        """A mask's pixels: bool H x W, True inside (read from ``mask_file`` once)."""
        if "inside" not in self._loaded:
            self._loaded["inside"] = read_fov_mask(self.mask_file)
        return self._loaded["inside"]

    def region(self, width: int, height: int, margin_px: float = 0.0) -> np.ndarray:
        """uint8 mask (255 inside) of this region in a width x height image, shrunk by ``margin_px``
        (a negative margin grows it)."""
        mask = np.zeros((height, width), np.uint8)
        if self.kind == "circle":
            r = self.r - margin_px
            if max(abs(self.cx), abs(self.cy), abs(r)) < 2 ** 20:
                cv2.circle(mask, (int(round(self.cx)), int(round(self.cy))), max(int(round(r)), 0), 255, -1)
            elif r > 0:  # beyond OpenCV's int coordinates: the implicit equation at pixel centres
                yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
                mask[(xx - self.cx) ** 2 + (yy - self.cy) ** 2 <= r * r] = 255
        elif self.kind == "ellipse":
            # the implicit equation at pixel centres: exact, where cv2.ellipse would round centre and axes
            a, b = self.a - margin_px, self.b - margin_px
            if a > 0 and b > 0:
                yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
                c, s = np.cos(np.radians(self.angle_deg)), np.sin(np.radians(self.angle_deg))
                u = (xx - self.cx) * c + (yy - self.cy) * s
                v = -(xx - self.cx) * s + (yy - self.cy) * c
                mask[(u / a) ** 2 + (v / b) ** 2 <= 1.0] = 255
        else:
            inside = self.inside()
            if inside.shape != (height, width):
                raise CalibrationError(f"field-of-view mask '{self.mask_file}' is {inside.shape[1]}x"
                                       f"{inside.shape[0]}, the camera is {width}x{height}; a mask must have "
                                       f"its camera's size")
            src = inside.astype(np.uint8)
            if margin_px > 0:  # keep pixels farther than the margin from the nearest outside pixel
                mask[cv2.distanceTransform(src, cv2.DIST_L2, 5) > margin_px] = 255
            elif margin_px < 0:  # add outside pixels within -margin of the nearest inside pixel
                mask[cv2.distanceTransform(1 - src, cv2.DIST_L2, 5) <= -margin_px] = 255
            else:
                mask[inside] = 255
        return mask


def read_fov_mask(path) -> np.ndarray:
    """A field-of-view mask image as bool H x W (non-zero in any channel = inside)."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise CalibrationError(f"field-of-view mask '{path}': missing or not an image; give a PNG of the "
                               f"camera's size, non-zero inside the field of view")
    return np.any(image != 0, axis=2) if image.ndim == 3 else image != 0


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...] = (0.0,) * N_DIST
    # the scope's circular field of view: radius in pixels about (cx, cy); 0 = none
    fov_radius_px: float = 0.0
    # any other field of view (an off-centre circle, an ellipse, a mask); it overrides fov_radius_px. A circle
    # about (cx, cy) is kept as fov_radius_px alone, so that both ways of giving it make equal cameras
    fov: FieldOfView | None = None

    def __post_init__(self) -> None:
        if len(self.dist) != N_DIST:
            object.__setattr__(self, "dist", tuple(self.dist) + (0.0,) * (N_DIST - len(self.dist)))
        fov = self.fov
        if fov is not None and fov.kind == "circle":
            object.__setattr__(self, "fov_radius_px", fov.r)  # consumers that know only a radius still see it
            if (fov.cx, fov.cy) == (self.cx, self.cy):
                object.__setattr__(self, "fov", None)

    @staticmethod
    def from_paper_model(width, height, fx, fy, cx, cy, k=(0.0, 0.0, 0.0), t=(0.0, 0.0), p=(0.0, 0.0),
                         fov_radius_px: float = 0.0) -> "CameraModel":
        """The seed paper's model: radial k1..k3, tangential t1 t2, thin prism p = (px, py)."""
        dist = (k[0], k[1], t[0], t[1], k[2], 0.0, 0.0, 0.0, p[0], 0.0, p[1], 0.0)
        return CameraModel(width, height, fx, fy, cx, cy, dist, fov_radius_px)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist_array(self) -> np.ndarray:
        return np.asarray(self.dist, dtype=np.float64)

    def project(self, points_camera: np.ndarray) -> np.ndarray:
        """Distorted pixel coordinates (N, 2) of camera-frame points (N, 3) (z > 0)."""
        pts = np.asarray(points_camera, dtype=np.float64).reshape(-1, 1, 3)
        uv, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), self.K, self.dist_array)
        return uv.reshape(-1, 2)

    def undistort_pixels(self, uv: np.ndarray) -> np.ndarray:
        """Distorted pixels -> pixels of the ideal pinhole camera with the same K."""
        pts = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.undistortPointsIter(
            pts, self.K, self.dist_array, None, self.K,
            (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10),
        ).reshape(-1, 2)

    def undistort_maps(self, K: np.ndarray | None = None,
                       size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """cv2.remap maps from the distorted frame to the undistorted pinhole image with ``K`` (default: the same
        K) at ``size`` (default: the same size)."""
        return cv2.initUndistortRectifyMap(self.K, self.dist_array, None, self.K if K is None else K,
                                           size or (self.width, self.height), cv2.CV_32FC1)

    def undistorted_outline(self, K: np.ndarray) -> np.ndarray:
        """The outline of the field of view in the frame (the frame's edge closes it), as pixels of the pinhole
        ``K`` (the same rays), (N, 2); only points that the lens model gives back (beyond a fold of the model a
        point undistorts to a wrong ray, finite but far)."""
        padded = cv2.copyMakeBorder(self.fov_mask(), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
        contours, _ = cv2.findContours(padded, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not contours:
            return np.zeros((0, 2))
        uv = np.concatenate([c.reshape(-1, 2) for c in contours]).astype(np.float64) - 1.0
        rays = cv2.undistortPointsIter(uv.reshape(-1, 1, 2), self.K, self.dist_array, None, None,
                                       (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)).reshape(-1, 2)
        ok = np.isfinite(rays).all(axis=1)
        back = self.project(np.column_stack([rays[ok], np.ones(int(ok.sum()))]))
        ok[ok] = np.linalg.norm(back - uv[ok], axis=1) <= 1.0
        return rays[ok] @ K[:2, :2].T + K[:2, 2]

    def seen_region(self, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
        """Which pixels of a pinhole image this camera sees (bool), from the image's undistortion maps
        (``undistort_maps``: each pixel's place in the frame): inside the frame and its field of view, and
        before any fold of the lens model, where the map from the pinhole image to the frame keeps its
        orientation (its Jacobian's determinant positive, in the region about the principal point). Beyond a
        fold a model maps rays back into the frame and would paint a ghost of it."""
        h, w = map_x.shape
        inside = cv2.remap(self.fov_mask(), map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                           borderValue=0) > 0
        dxx, dxy = np.gradient(map_x, axis=1), np.gradient(map_x, axis=0)
        dyx, dyy = np.gradient(map_y, axis=1), np.gradient(map_y, axis=0)
        unfolded = ((dxx * dyy - dxy * dyx) > 0) & inside
        n, labels = cv2.connectedComponents(unfolded.astype(np.uint8), connectivity=4)
        if n <= 2:
            return unfolded
        # the region about the principal point: the component holding the pixel nearest to the frame's centre
        d = (map_x - self.cx) ** 2 + (map_y - self.cy) ** 2
        centre = np.unravel_index(np.argmin(np.where(unfolded, d, np.inf)), d.shape)
        return labels == labels[centre]

    @property
    def field_of_view(self) -> FieldOfView | None:
        """The field of view as a region (``fov``, or the circle of ``fov_radius_px``); None: the whole image."""
        if self.fov is not None:
            return self.fov
        return FieldOfView.circle(self.cx, self.cy, self.fov_radius_px) if self.fov_radius_px > 0 else None

    def fov_mask(self, margin_px: float = 0.0) -> np.ndarray:
        """uint8 mask (255 inside) of the field of view in the distorted image, shrunk by ``margin_px``."""
        fov = self.field_of_view
        if fov is None:
            return np.full((self.height, self.width), 255, np.uint8)
        return fov.region(self.width, self.height, margin_px)


@dataclass(frozen=True)
class Rig:
    """The cameras of a scope, rigidly mounted together: camera 0 is the reference (its pose is the rig's
    pose, T_world_camera everywhere else); ``T_cam0_cam[k]`` maps points from camera k to camera 0 (identity
    for k = 0). A stereo scope is a rig of two; its extrinsics are held by bundle adjustment within their
    calibrated 1-sigma uncertainty (``sigma_rotation_rad``, ``sigma_translation_m``)."""

    cameras: tuple[CameraModel, ...]
    T_cam0_cam: tuple[np.ndarray, ...]
    sigma_rotation_rad: float = 0.0005
    sigma_translation_m: float = 0.0001

    def __post_init__(self) -> None:
        if len(self.cameras) != len(self.T_cam0_cam) or not self.cameras:
            raise ValueError("a rig needs one T_cam0_cam per camera")
        if not np.allclose(self.T_cam0_cam[0], np.eye(4)):
            raise ValueError("T_cam0_cam of camera 0 must be the identity")

    @staticmethod
    def mono(camera: CameraModel) -> "Rig":
        return Rig((camera,), (np.eye(4),))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def is_stereo(self) -> bool:
        return len(self.cameras) >= 2

    def baseline_m(self, k: int = 1) -> float:
        return float(np.linalg.norm(self.T_cam0_cam[k][:3, 3]))


def pinhole_canvas(cameras: list[CameraModel], max_pad: float) -> tuple[np.ndarray, tuple[int, int]]:
    """(K, (width, height)) of a pinhole image with the first camera's focal lengths that holds every camera's
    field of view undistorted (each camera's rays in the first's K; a stereo partner is undistorted to it): the
    first camera's frame, grown on each side by what its outline reaches beyond it, by at most ``max_pad`` of
    the frame's width or height. A lens without distortion, or a field of view inside the frame, grows nothing."""
    first = cameras[0]
    K = first.K
    w, h = first.width, first.height
    lo, hi = np.array([0.0, 0.0]), np.array([w - 1.0, h - 1.0])
    for cam in cameras:
        pts = cam.undistorted_outline(K)
        if len(pts):
            lo = np.minimum(lo, pts.min(axis=0))
            hi = np.maximum(hi, pts.max(axis=0))
    cap = np.array([max_pad * w, max_pad * h])
    before = np.minimum(np.ceil(-lo - 0.5).clip(0.0), cap).astype(int)  # (a fraction of a pixel is no column)
    after = np.minimum(np.ceil(hi - np.array([w - 1.0, h - 1.0]) - 0.5).clip(0.0), cap).astype(int)
    K_canvas = K.copy()
    K_canvas[0, 2] += before[0]
    K_canvas[1, 2] += before[1]
    return K_canvas, (int(w + before[0] + after[0]), int(h + before[1] + after[1]))
