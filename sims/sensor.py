"""The simulated camera's sensor: scene radiance -> raw Bayer mosaic (DN) -> DNG bytes.

Radiometric chain for the pixel at (row y, column x), whose colour filter is channel c:

1. Image-plane irradiance (the camera equation): ``E = L_c * pi / (4 N^2) * V(x, y)`` with ``L_c``
   the scene radiance of the pixel's channel (linear, arbitrary W/(sr m^2)-like units), ``N`` the
   f-number and ``V`` the vignetting (natural cos^4 fall-off or a polynomial).
2. Mean photo-electrons: ``mu = QE_c * photon_flux * pitch^2 * t * E``, plus the dark signal
   ``dark_current_e_s * t``.
3. Shot noise: Poisson(mu) (the dark signal is Poisson too). Above ``_GAUSS_ABOVE`` electrons a
   Gaussian with the same mean and variance replaces it (3-4x faster; the Poisson skewness there
   is 1/sqrt(mu) < 0.03, far below anything a measurement here can see).
4. Full-well saturation: electrons clip at ``full_well_e`` (no blooming into neighbours).
5. Read noise: Gaussian, ``read_noise_e`` electrons RMS, input-referred (independent of ISO).
6. Gain and ADC: ``DN = round(e / e_per_dn(iso) + black_level)`` clipped to ``[0, white_level]``;
   ``e_per_dn(iso) = e_per_dn_base * base_iso / iso`` so ISO is an analogue gain.

Lens distortion is not applied here: the renderer shoots one ray through the centre of each pixel
of the *distorted* image (``CameraModel.pixel_rays`` undistorts), so the rendered radiance already
carries the distortion exactly.

Everything is vectorised numpy over the mosaic; randomness comes from an explicit
``numpy.random.Generator``.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field, replace

import numpy as np

from .dng import write_dng

CFA_PATTERNS = ("RGGB", "GRBG", "BGGR", "GBRG")
_CHANNEL = {"R": 0, "G": 1, "B": 2}
# Shot noise switches from exact Poisson to its Gaussian approximation above this mean (electrons).
_GAUSS_ABOVE = 1000.0
# Default gain: the ADC reaches the white level at this fraction of the full well.
_ADC_HEADROOM = 0.97
# XYZ (D65) -> linear sRGB: the simulator's RGB primaries are sRGB's.
_XYZ_TO_SRGB = np.array([[3.2404542, -1.5371385, -0.4985314],
                         [-0.9692660, 1.8760108, 0.0415560],
                         [0.0556434, -0.2040259, 1.0572252]])


@functools.lru_cache(maxsize=8)
def _vignetting(kind, strength, coeffs, height, width, focal_px, cx, cy) -> np.ndarray:
    """Relative illumination map (cached: every frame of a camera shares it), read-only."""
    if kind == "none":
        v = np.ones((height, width))
    else:
        ys, xs = np.ogrid[0:height, 0:width]
        r2 = (xs - cx) ** 2 + (ys - cy) ** 2
        if kind == "cos4":
            v = 1.0 - strength * (1.0 - (focal_px ** 2 / (focal_px ** 2 + r2)) ** 2)
        else:
            rn2 = r2 / (((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2)
            v = 1.0 + sum(a * rn2 ** k for k, a in enumerate(coeffs, start=1))
            if np.any(v <= 0):
                raise ValueError(f"vignetting_coeffs {coeffs} make the relative illumination <= 0 "
                                 "inside the image")
    v.flags.writeable = False
    return v


@dataclass(frozen=True)
class ExpectedRaw:
    """Noise-free expectation of a raw frame (what :meth:`SensorModel.expose` scatters around).

    Attributes
    ----------
    mean_dn : ndarray of shape (H, W), float64
        Mean digital number per pixel, before clipping to the white level.
    sigma_dn : ndarray of shape (H, W), float64
        Standard deviation in DN: shot (signal + dark), read and quantisation noise
        (``sqrt(g^2 (mu + dark + read^2) + 1/12)`` with ``g`` the DN per electron).
    saturated : ndarray of shape (H, W), bool
        Pixels whose mean signal reaches the full well or the white level (within 5 sigma): these
        read ``min(white level, full-well DN)``, not the linear value.
    """

    mean_dn: np.ndarray
    sigma_dn: np.ndarray
    saturated: np.ndarray


@dataclass(frozen=True)
class SensorModel:
    """A CMOS sensor behind a Bayer colour filter array (the default: a 14-bit full-frame body).

    Attributes
    ----------
    pixel_pitch_um : float
        Pixel pitch, micrometres (5.9 um: a 24-megapixel full-frame sensor).
    quantum_efficiency : 3 floats
        QE of the R, G, B filtered pixels (electrons per photon). Their ratios are the camera's
        white balance: ``AsShotNeutral = QE / QE_G`` in the DNG.
    photon_flux : float
        Photons per second per square micrometre produced by unit image-plane irradiance (the
        scale that ties the renderer's arbitrary radiance units to photons).
    full_well_e : float
        Full-well capacity, electrons.
    read_noise_e : float
        Read noise, electrons RMS (input-referred).
    dark_current_e_s : float
        Dark current, electrons per second per pixel.
    bit_depth : int
        ADC bits; the white level is ``2**bit_depth - 1``.
    black_level : int
        Black (pedestal) level, DN.
    cfa_pattern : str
        2x2 colour-filter tile from the top-left, row-major: one of ``CFA_PATTERNS``.
    base_iso : float
        ISO at which ``e_per_dn_base`` applies.
    e_per_dn_base : float or None
        Conversion gain at ``base_iso``, electrons per DN; None: ``0.97 full_well_e / (white -
        black)``, i.e. the ADC clips at 97 % of the full well (as on most bodies), so saturated
        pixels read exactly the white level at ISO >= base.
    vignetting : str
        ``"cos4"`` (natural fall-off of the field angle, needs the focal length), ``"poly"``
        (``1 + a1 r^2 + a2 r^4 + a3 r^6`` with ``r`` the distance from the principal point over
        the half-diagonal) or ``"none"``.
    vignetting_strength : float
        For ``"cos4"``: 0 (none) .. 1 (full natural cos^4): ``V = 1 - s (1 - cos^4)``.
    vignetting_coeffs : tuple of floats
        ``(a1, a2, a3)`` for ``"poly"``.
    make, model : str
        Written to the DNG.
    """

    pixel_pitch_um: float = 5.9
    quantum_efficiency: tuple[float, float, float] = (0.38, 0.50, 0.34)
    photon_flux: float = 1.0e7
    full_well_e: float = 50_000.0
    read_noise_e: float = 3.0
    dark_current_e_s: float = 0.2
    bit_depth: int = 14
    black_level: int = 512
    cfa_pattern: str = "RGGB"
    base_iso: float = 100.0
    e_per_dn_base: float | None = None
    vignetting: str = "cos4"
    vignetting_strength: float = 1.0
    vignetting_coeffs: tuple[float, ...] = field(default_factory=tuple)
    make: str = "gonio"
    model: str = "SimCam FF14"

    def __post_init__(self) -> None:
        qe = tuple(float(q) for q in np.ravel(self.quantum_efficiency))
        if len(qe) != 3 or not all(0 < q <= 1 for q in qe):
            raise ValueError(f"quantum_efficiency must be three values in (0, 1], got {self.quantum_efficiency!r}")
        object.__setattr__(self, "quantum_efficiency", qe)
        for name in ("pixel_pitch_um", "photon_flux", "full_well_e", "base_iso"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("read_noise_e", "dark_current_e_s"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not 8 <= int(self.bit_depth) <= 16:
            raise ValueError(f"bit_depth must be 8..16 (raw is stored as uint16), got {self.bit_depth!r}")
        if not 0 <= int(self.black_level) < self.white_level:
            raise ValueError(f"black_level must be in [0, white level {self.white_level}), got {self.black_level!r}")
        pattern = str(self.cfa_pattern).upper()
        if pattern not in CFA_PATTERNS:
            raise ValueError(f"cfa_pattern must be one of {CFA_PATTERNS}, got {self.cfa_pattern!r}")
        object.__setattr__(self, "cfa_pattern", pattern)
        if self.e_per_dn_base is not None and not self.e_per_dn_base > 0:
            raise ValueError(f"e_per_dn_base must be > 0 (or None), got {self.e_per_dn_base!r}")
        if self.vignetting not in ("cos4", "poly", "none"):
            raise ValueError(f"vignetting must be 'cos4', 'poly' or 'none', got {self.vignetting!r}")
        if not 0 <= self.vignetting_strength <= 1:
            raise ValueError(f"vignetting_strength must be in [0, 1], got {self.vignetting_strength!r}")
        coeffs = tuple(float(a) for a in self.vignetting_coeffs)
        if self.vignetting == "poly" and not 1 <= len(coeffs) <= 3:
            raise ValueError(f"vignetting='poly' needs 1-3 vignetting_coeffs (a1, a2, a3), got {coeffs!r}")
        object.__setattr__(self, "vignetting_coeffs", coeffs)

    # -- presets ------------------------------------------------------------------------------
    @classmethod
    def full_frame(cls, **overrides) -> "SensorModel":
        """The default body: 14-bit, 5.9 um pixels, 50 ke- full well, 3 e- read noise, RGGB."""
        return replace(cls(), **overrides)

    @classmethod
    def compact(cls, **overrides) -> "SensorModel":
        """A small-pixel 12-bit sensor (1.55 um, 6 ke- full well, GRBG, black 64), for tests.

        Its photon flux is scaled so a given radiance fills the same fraction of the full well as
        on :meth:`full_frame`.
        """
        base = cls(pixel_pitch_um=1.55, quantum_efficiency=(0.45, 0.60, 0.40),
                   photon_flux=1.0e7 * (5.9 / 1.55) ** 2 * 6000 / 50_000 * 0.50 / 0.60,
                   full_well_e=6000.0, read_noise_e=2.0, dark_current_e_s=1.0, bit_depth=12,
                   black_level=64, cfa_pattern="GRBG", vignetting="poly",
                   vignetting_coeffs=(-0.25, 0.05), model="SimCam C12")
        return replace(base, **overrides)

    # -- derived quantities -------------------------------------------------------------------
    @property
    def white_level(self) -> int:
        """Largest raw value, DN."""
        return 2 ** int(self.bit_depth) - 1

    def e_per_dn(self, iso: float) -> float:
        """Conversion gain at ``iso``, electrons per DN."""
        if not iso > 0:
            raise ValueError(f"iso must be > 0, got {iso!r}")
        base = self.e_per_dn_base if self.e_per_dn_base is not None else \
            _ADC_HEADROOM * self.full_well_e / (self.white_level - self.black_level)
        return base * self.base_iso / float(iso)

    @property
    def as_shot_neutral(self) -> tuple[float, float, float]:
        """Camera response to a neutral (R = G = B) scene, normalised to green."""
        q = np.asarray(self.quantum_efficiency)
        return tuple(float(v) for v in q / q[1])

    def cfa_channels(self, height: int, width: int) -> np.ndarray:
        """Colour channel (0 R, 1 G, 2 B) of every pixel of an (height, width) mosaic -> (H, W) int."""
        tile = np.array([_CHANNEL[c] for c in self.cfa_pattern]).reshape(2, 2)
        return np.tile(tile, ((height + 1) // 2, (width + 1) // 2))[:height, :width]

    def mosaic(self, rgb: np.ndarray) -> np.ndarray:
        """The value of each pixel's own colour channel of an (H, W, 3) image -> (H, W)."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"image must have shape (H, W, 3), got {rgb.shape}")
        ch = self.cfa_channels(*rgb.shape[:2])
        return np.take_along_axis(rgb, ch[..., None], axis=2)[..., 0]

    def vignetting_map(self, height: int, width: int, *, focal_px: float | None = None,
                       principal_point: tuple[float, float] | None = None) -> np.ndarray:
        """Relative illumination ``V`` in (0, 1] per pixel -> (H, W) float64.

        Parameters
        ----------
        height, width : int
            Image size, pixels.
        focal_px : float, optional
            Focal length in pixels; required for ``vignetting="cos4"`` (the field angle of pixel
            ``p`` is ``atan(|p - c| / f)``).
        principal_point : (cx, cy), optional
            Pixel coordinates of the optical axis; default the image centre.
        """
        if self.vignetting == "cos4" and (focal_px is None or not focal_px > 0):
            raise ValueError(f"vignetting='cos4' needs focal_px > 0 (the focal length in pixels), got {focal_px!r}")
        cx, cy = principal_point if principal_point is not None else ((width - 1) / 2, (height - 1) / 2)
        return _vignetting(self.vignetting, self.vignetting_strength, self.vignetting_coeffs, int(height),
                           int(width), None if focal_px is None else float(focal_px), float(cx), float(cy))

    # -- the forward model --------------------------------------------------------------------
    def _check_exposure(self, radiance, exposure_s, iso, fnumber) -> np.ndarray:
        rad = np.asarray(radiance)
        if rad.ndim != 3 or rad.shape[2] != 3:
            raise ValueError(f"radiance must be a linear (H, W, 3) image, got shape {rad.shape}")
        if not np.all(np.isfinite(rad)):
            raise ValueError("radiance contains NaN or infinite values")
        if np.any(rad < 0):
            raise ValueError(f"radiance must be >= 0, minimum is {float(rad.min())}")
        if not exposure_s > 0:
            raise ValueError(f"exposure_s must be > 0 seconds, got {exposure_s!r}")
        if not iso > 0:
            raise ValueError(f"iso must be > 0, got {iso!r}")
        if not fnumber > 0:
            raise ValueError(f"fnumber must be > 0, got {fnumber!r}")
        return rad

    def _electrons_per_radiance(self, shape, exposure_s, fnumber, focal_px, principal_point) -> np.ndarray:
        """Mean photo-electrons per unit radiance of each pixel's channel -> (H, W)."""
        h, w = shape
        qe = np.asarray(self.quantum_efficiency)[self.cfa_channels(h, w)]
        optics = np.pi / (4.0 * fnumber ** 2) * self.vignetting_map(
            h, w, focal_px=focal_px, principal_point=principal_point)
        return qe * optics * (self.photon_flux * self.pixel_pitch_um ** 2 * exposure_s)

    def mean_electrons(self, radiance: np.ndarray, exposure_s: float, *, fnumber: float = 8.0,
                       focal_px: float | None = None,
                       principal_point: tuple[float, float] | None = None) -> np.ndarray:
        """Mean photo-electrons per pixel (no dark signal, no saturation) -> (H, W) float64.

        ``radiance`` is the linear (H, W, 3) image; ``exposure_s`` seconds; ``fnumber`` the lens
        aperture; ``focal_px`` / ``principal_point`` as in :meth:`vignetting_map`.
        """
        rad = self._check_exposure(radiance, exposure_s, self.base_iso, fnumber)
        return self.mosaic(rad).astype(np.float64) * self._electrons_per_radiance(
            rad.shape[:2], exposure_s, fnumber, focal_px, principal_point)

    def expose(self, radiance: np.ndarray, exposure_s: float, iso: float = 100.0,
               rng: np.random.Generator | int | None = None, *, fnumber: float = 8.0,
               focal_px: float | None = None,
               principal_point: tuple[float, float] | None = None) -> np.ndarray:
        """Take a raw frame: radiance -> noisy, saturated, quantised Bayer mosaic.

        Parameters
        ----------
        radiance : ndarray of shape (H, W, 3)
            Linear scene radiance seen by each pixel (RGB, >= 0), e.g. ``RenderResult.radiance``.
        exposure_s : float
            Exposure time, seconds.
        iso : float
            ISO setting (analogue gain relative to ``base_iso``).
        rng : numpy.random.Generator or int, optional
            Source of the noise (a seed is turned into ``default_rng(seed)``).
        fnumber : float
            Aperture f-number.
        focal_px, principal_point
            Optics for the vignetting (see :meth:`vignetting_map`).

        Returns
        -------
        ndarray of shape (H, W), uint16
            Raw DN in ``cfa_pattern`` order, ``black_level`` .. ``white_level``.
        """
        rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        mu = self.mean_electrons(radiance, exposure_s, fnumber=fnumber, focal_px=focal_px,
                                 principal_point=principal_point)
        mu += self.dark_current_e_s * exposure_s
        electrons = np.empty_like(mu)
        low = mu < _GAUSS_ABOVE
        electrons[low] = rng.poisson(mu[low])
        high = ~low
        electrons[high] = mu[high] + np.sqrt(mu[high]) * rng.standard_normal(int(high.sum()))
        np.minimum(electrons, self.full_well_e, out=electrons)
        electrons += self.read_noise_e * rng.standard_normal(electrons.shape)
        dn = np.rint(electrons / self.e_per_dn(iso) + self.black_level)
        return np.clip(dn, 0, self.white_level).astype(np.uint16)

    def expected_raw(self, radiance: np.ndarray, exposure_s: float, iso: float = 100.0, *,
                     fnumber: float = 8.0, focal_px: float | None = None,
                     principal_point: tuple[float, float] | None = None) -> ExpectedRaw:
        """Mean and standard deviation of :meth:`expose`'s output, per pixel (same arguments)."""
        mu = self.mean_electrons(radiance, exposure_s, fnumber=fnumber, focal_px=focal_px,
                                 principal_point=principal_point)
        mu += self.dark_current_e_s * exposure_s
        g = 1.0 / self.e_per_dn(iso)
        mean = mu * g + self.black_level
        sigma = np.sqrt(g ** 2 * (mu + self.read_noise_e ** 2) + 1.0 / 12.0)
        sat = (mu + 5 * np.sqrt(mu) >= self.full_well_e) | (mean + 5 * sigma >= self.white_level)
        return ExpectedRaw(mean_dn=mean, sigma_dn=sigma, saturated=sat)

    def saturation_dn(self, iso: float) -> int:
        """The raw value of a saturated pixel at ``iso``: the full well or the ADC's white level."""
        return int(min(self.white_level, np.rint(self.full_well_e / self.e_per_dn(iso) + self.black_level)))

    # -- the inverse --------------------------------------------------------------------------
    def raw_to_radiance(self, raw: np.ndarray, exposure_s: float, iso: float = 100.0, *,
                        fnumber: float = 8.0, focal_px: float | None = None,
                        principal_point: tuple[float, float] | None = None) -> np.ndarray:
        """Linear radiance of each pixel's own channel from a raw mosaic -> (H, W) float64.

        Black-subtracted, dark-subtracted, white-normalised and exposure-normalised: the inverse
        of the mean of :meth:`expose` (unbiased below saturation). Saturated pixels come back as
        a lower bound.
        """
        raw = np.asarray(raw)
        if raw.ndim != 2:
            raise ValueError(f"raw must be a 2-D mosaic, got shape {raw.shape}")
        if not exposure_s > 0:
            raise ValueError(f"exposure_s must be > 0 seconds, got {exposure_s!r}")
        if not fnumber > 0:
            raise ValueError(f"fnumber must be > 0, got {fnumber!r}")
        electrons = (raw.astype(np.float64) - self.black_level) * self.e_per_dn(iso) \
            - self.dark_current_e_s * exposure_s
        return electrons / self._electrons_per_radiance(raw.shape, exposure_s, fnumber, focal_px,
                                                        principal_point)

    # -- file ---------------------------------------------------------------------------------
    def color_matrix(self) -> np.ndarray:
        """DNG ColorMatrix1 (XYZ D65 -> camera RGB): sRGB primaries times the QE ratios, (3, 3)."""
        return np.diag(self.as_shot_neutral) @ _XYZ_TO_SRGB

    def to_dng(self, raw: np.ndarray, *, exposure_s: float | None = None, iso: float | None = None,
               fnumber: float | None = None, datetime: str | None = None) -> bytes:
        """Encode a raw mosaic from :meth:`expose` as DNG bytes (black/white level, CFA pattern,
        colour matrix, as-shot neutral white balance and the exposure settings as tags)."""
        raw = np.asarray(raw)
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise ValueError(f"raw must be a (H, W) uint16 mosaic, got shape {raw.shape} dtype {raw.dtype}")
        if raw.size and int(raw.max()) > self.white_level:
            raise ValueError(f"raw holds values above the white level {self.white_level}")
        return write_dng(raw, cfa_pattern=self.cfa_pattern, black_level=self.black_level,
                         white_level=self.white_level, color_matrix=self.color_matrix(),
                         as_shot_neutral=self.as_shot_neutral, make=self.make, model=self.model,
                         exposure_s=exposure_s, iso=iso, fnumber=fnumber, datetime=datetime)
