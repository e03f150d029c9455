"""The eight parts of one procedural head as closed-form 2-D fields (:class:`HeadBuilder`): head with its
relief and face paint, eyes, ears, torso, backdrop, hair, glasses and beard.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from lp3d.teachers.procedural_fields import (
    ABSENT_PART,
    EMPTY_FIELD,
    HAIRSTYLE_SHAPES,
    PartFields,
    Textures,
    colour_logits,
    gauss,
    smoothstep,
    tint,
)
from lp3d.teachers.procedural_identity import HeadParams


@dataclass(frozen=True)
class _Geometry:
    """Where the teacher versions' shapes differ. v2's surfaces gather their opacity over a few
    centimetres (soft on the 48 + 48 sampler's scale), so its glasses are thicker and its edges
    softer than v1's: v1's steep edges and 5.5 mm glasses wire are thinner than the sampler resolves
    where a ray grazes them. (Hair 1.5x as thick covers the face better from the side, but its edges
    then exceed 0.15 against 192 + 192 samples: 0.166; kept at v1's thickness.)"""

    #: How steeply the hair's A rises beyond its silhouette.
    hair_wall: float
    #: Half width of the beard mask's edge (world units).
    beard_edge: float
    #: Half thickness of the glasses' frame wire across the view and along it.
    glasses_wire: float
    glasses_depth: float


_GEOMETRY = {
    1: _Geometry(hair_wall=40.0, beard_edge=0.004, glasses_wire=0.0055, glasses_depth=0.0055),
    2: _Geometry(hair_wall=4.0, beard_edge=0.012, glasses_wire=0.0075, glasses_depth=0.014),
}


class HeadBuilder:
    """The eight parts of one identity, from the texel centres ``coords`` (R,): ``x`` (1, R) indexes
    columns; ``y`` = ``z`` (R, 1) index rows, read as y in the (x, y) fields (A, fc) and as z in the
    (x, z) fields (B, gc)."""

    def __init__(self, p: HeadParams, coords: np.ndarray, textures: Textures, *, version: int) -> None:
        self.p = p
        self.geometry = _GEOMETRY[version]
        self.coords = coords
        self.tex = textures
        self.x = coords[None, :]
        self.y = self.z = coords[:, None]
        self.ax = np.abs(self.x)
        self.yc = 0.03  # head centre height
        self.zc = 0.02  # head centre depth (EG3D's FFHQ cameras look at z = 0.2, about the face)
        self.ey = self.yc + 0.012  # eye height
        self.skin = colour_logits(p.skin_rgb)
        self.hair_logit = colour_logits(p.hair_rgb)
        self.hair_lightness = float(np.mean(p.hair_rgb))

    def window(self, x0: float, x1: float, y0: float, y1: float) -> tuple[slice, slice]:
        """Row and column slices of the texels with y0 <= y <= y1 and x0 <= x <= x1."""
        c = self.coords
        rows = slice(int(np.searchsorted(c, y0)), int(np.searchsorted(c, y1, side="right")))
        cols = slice(int(np.searchsorted(c, x0)), int(np.searchsorted(c, x1, side="right")))
        return rows, cols

    def parts(self) -> list[PartFields]:
        p = self.p
        return [
            self.head(),
            self.hair(),
            self.eyes(),
            self.ears(),
            self.torso(),
            self.background(),
            self.glasses() if p.glasses else ABSENT_PART,
            self.beard() if p.beard else ABSENT_PART,
        ]

    # -- head -------------------------------------------------------------------------------------
    @property
    def nose_tip_y(self) -> float:
        return self.ey - 0.30 * self.p.head_height * (0.85 + 0.15 * self.p.nose_size)

    @property
    def mouth_y(self) -> float:
        return self.yc - 0.58 * self.p.head_height

    def head_width(self, y: np.ndarray | float) -> np.ndarray | float:
        """Half-width of the skull ellipse at height y (narrower toward the jaw)."""
        p = self.p
        t = (y - self.yc) / p.head_height
        return p.head_width * (1.0 - (1.0 - p.jaw_width) * smoothstep(0.15, -1.0, t))

    def skull_A(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
        """Front-view field of the plain skull: ``(x / width(y))^2 + t^2``."""
        t = (y - self.yc) / self.p.head_height
        return (x / self.head_width(y)) ** 2 + t * t

    def relief(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Face relief (world units toward +z) over (x, y): nose, sockets, brow ridge, lips, chin."""
        p = self.p
        ax = np.abs(x)
        re = p.eye_size
        ns = p.nose_size
        # Nose: a ridge from the brow to the tip, wider and higher toward the tip, with wings.
        y_tip = self.nose_tip_y
        y_top = self.ey + 0.008
        along = np.clip((y - y_tip) / (y_top - y_tip), 0.0, 1.0)  # 0 at the tip, 1 at the bridge top
        height = (
            0.032 * ns * (0.25 + 0.75 * (1.0 - along) ** 1.4) * smoothstep(y_top + 0.005, y_top - 0.02, y)
        )
        under = smoothstep(y_tip - 0.017 * ns, y_tip, y)  # the underside turns back to the lip
        width = 0.007 + 0.011 * ns * (1.0 - along) ** 1.5
        across = np.cos(np.clip(x / width, -1.0, 1.0) * (np.pi / 2)) ** 2
        r = height * under * across
        wings = np.exp(-(((ax - 0.75 * width) / (0.55 * width)) ** 2)) * gauss(
            (y - y_tip + 0.008 * ns) / 0.008
        )
        r = r + 0.012 * ns * wings
        # Eye sockets (the eyeballs show through an almond-shaped opening), brow ridge, cheekbones.
        dx = ax - p.eye_spacing
        r = r - 0.011 * gauss(dx / (1.3 * re)) * gauss((y - self.ey) / (0.55 * re))
        r = r + 0.005 * gauss(dx / 0.035) * gauss((y - self.ey - 1.9 * re) / 0.010)
        r = r + 0.005 * gauss((ax - 0.07) / 0.03) * gauss((y - self.ey + 0.04) / 0.02)
        # Lips: two rolls either side of the mouth line, and the chin.
        ym, lf = self.mouth_y, p.lip_fullness
        r = r + 0.007 * lf * np.exp(-((x / (0.026 * lf)) ** 4)) * gauss((y - ym - 0.005 * lf) / (0.005 * lf))
        r = r + 0.008 * lf * np.exp(-((x / (0.024 * lf)) ** 4)) * gauss((y - ym + 0.006 * lf) / (0.006 * lf))
        r = r - 0.004 * gauss(x / 0.025) * gauss((y - ym) / 0.002)
        r = r + 0.01 * gauss(x / 0.03) * gauss((y - self.yc + 0.86 * p.head_height) / 0.02)
        return r

    def head_A(self, x: np.ndarray, y: np.ndarray, A0: np.ndarray) -> np.ndarray:
        """Front-view field of the head with the face relief, from the plain skull's ``A0`` at (x, y):
        the face's surface is the height field ``zc + D (sqrt(1 - A0) + relief / D)``, so
        ``A = 1 - (sqrt(1 - A0) + relief / D)^2``. A goes below 0 on the nose (down to about -0.5),
        within FIELD_CEILING, so plane 0 alone still decodes as empty."""
        q = np.sqrt(np.maximum(0.0, 1.0 - A0)) + self.relief(x, y) / self.p.head_depth
        return np.where(A0 < 1.0, 1.0 - np.maximum(q, 0.0) ** 2, A0)

    def head_B(self, z: np.ndarray) -> np.ndarray:
        # Steep behind the centre (power 6): the face relief barely moves the back of the skull.
        dz = z - self.zc
        D = self.p.head_depth
        return np.where(dz > 0, (dz / D) ** 2, (dz / (1.03 * D)) ** 6)

    def face_z(self, x: float, y: float) -> float:
        """Depth of the plain skull's front surface at (x, y) (no relief)."""
        a = float(self.skull_A(x, y))
        return self.zc + self.p.head_depth * math.sqrt(max(0.0, 1.0 - a))

    def face_window(self) -> tuple[slice, slice]:
        """Where the face relief and paint live (they are negligible outside it)."""
        p = self.p
        return self.window(-0.13, 0.13, self.yc - p.head_height - 0.03, self.ey + 0.075)

    def head(self) -> PartFields:
        """The skull ellipsoid (narrowing to the jaw) with the face as relief, painted."""
        p, x, y, z = self.p, self.x, self.y, self.z
        A = self.skull_A(x, y)
        # Skin lit from one side and from above, over (x, y); over (x, z) the front is lit and the sides
        # and back fall off.
        fc = self.skin + (0.25 * p.light_x * x / p.head_width + 0.9 * (y - self.yc)).astype(np.float32)
        gc = (0.8 * (z - self.zc) / p.head_depth - 0.2).astype(np.float32)
        rows, cols = self.face_window()
        xw, yw = x[:, cols], y[rows, :]
        A[rows, cols] = self.head_A(xw, yw, A[rows, cols])
        fc[:, rows, cols] = self.face_paint(xw, yw, fc[:, rows, cols])
        return PartFields(A, self.head_B(z), fc, gc)

    def face_paint(self, x: np.ndarray, y: np.ndarray, fc: np.ndarray) -> np.ndarray:
        """The face painted over the lit skin ``fc`` (3, h, w) at (x (1, w), y (h, 1))."""
        p = self.p
        ax = np.abs(x)
        re = p.eye_size
        dx = ax - p.eye_spacing
        ym = self.mouth_y
        fc = fc.copy()
        brow_y = self.ey + 1.75 * re + 0.006 * (1.0 - (dx / 0.028) ** 2)
        brow = np.exp(-(((y - brow_y) / (0.0042 * p.brow_thickness)) ** 2)) * smoothstep(
            0.032, 0.024, np.abs(dx + 0.002)
        )
        fc += brow * (colour_logits(np.asarray(p.hair_rgb) * 0.6 + 0.04) - fc)
        # Upper lash line along the top of the eye opening.
        lid_y = self.ey + 0.62 * re * np.sqrt(np.maximum(0.0, 1.0 - (dx / (1.05 * re)) ** 2))
        liner = np.exp(-(((y - lid_y) / 0.0026) ** 2)) * smoothstep(1.15 * re, 0.8 * re, np.abs(dx))
        fc += liner * (colour_logits((0.08, 0.05, 0.05)) - fc)
        lf = p.lip_fullness
        lips = smoothstep(1.0, 0.75, (x / (0.027 * lf)) ** 2 + ((y - ym + 0.001) / (0.0115 * lf)) ** 2)
        fc += lips * (colour_logits(p.lip_rgb) - fc)
        fc -= 1.2 * gauss(x / (0.025 * lf)) * gauss((y - ym) / 0.0018)
        # Painted shading where the relief is too small to shade itself: the lid crease, the side of the
        # nose away from the light, under the nose and the lower lip; light on the nose ridge; nostrils.
        crease = gauss((y - self.ey - 0.95 * re) / 0.0035) * smoothstep(1.3 * re, 0.7 * re, np.abs(dx))
        y_tip = self.nose_tip_y
        h_up = self.ey + 0.012 - y_tip
        ns = p.nose_size
        side = -1.0 if p.light_x >= 0 else 1.0
        nose_side = gauss((x - side * 0.014 * ns) / 0.008) * gauss((y - y_tip - 0.4 * h_up) / (0.5 * h_up))
        under_nose = gauss(x / 0.014) * gauss((y - y_tip + 0.02 * ns) / 0.005)
        nostrils = gauss((ax - 0.008 * ns) / 0.0045) * gauss((y - y_tip + 0.012 * ns) / 0.0035)
        under_lip = gauss(x / 0.02) * gauss((y - ym + 0.02) / 0.005)
        ridge = gauss(x / 0.004) * (smoothstep(self.ey, y_tip, y) * smoothstep(y_tip - 0.012, y_tip, y))
        fc -= (
            0.5 * crease
            + (0.3 + 0.3 * abs(p.light_x)) * nose_side
            + 0.5 * under_nose
            + 1.4 * nostrils
            + 0.35 * under_lip
            - 0.35 * ridge
        )
        blush = gauss((ax - 0.072) / 0.028) * gauss((y - self.ey + 0.052) / 0.025)
        fc += 0.35 * blush * tint(0.6, -0.4, -0.3)
        if p.freckles > 0:
            area = gauss((ax - 0.05) / 0.04) * gauss((y - self.ey + 0.04) / 0.03)
            fc -= 0.9 * p.freckles * area * self.tex.dots[self.face_window()] * tint(0.6, 0.9, 1.1)
        return fc

    # -- eyes -------------------------------------------------------------------------------------
    def eyes(self) -> PartFields:
        """Two spheres (x enters A through |x|), set deep so only the almond opening shows."""
        p, z = self.p, self.z
        re, ex, ey = p.eye_size, p.eye_spacing, self.ey
        ez = self.face_z(ex, ey) - 0.88 * re
        reach = ex + 2.1 * re  # A >= 4 (f at its floor) beyond 2 radii: nothing to compute there
        rows, cols = self.window(-reach, reach, ey - 2.1 * re, ey + 2.1 * re)
        x, y = self.x[:, cols], self.y[rows, :]
        dx = np.abs(x) - ex
        r2 = (dx * dx + (y - ey) ** 2) / (re * re)
        r = np.sqrt(r2)
        fc = colour_logits((0.93, 0.91, 0.88)) - 0.6 * smoothstep(0.6, 0.95, r)  # corners in shadow
        fc = fc + smoothstep(0.56, 0.5, r) * (colour_logits(p.eye_rgb) - fc)
        fc = fc - 0.8 * smoothstep(0.3, 0.5, r) * smoothstep(0.56, 0.5, r)  # darker iris rim
        fc = fc + smoothstep(0.24, 0.2, r) * (colour_logits((0.02, 0.02, 0.02)) - fc)
        glint = gauss((dx + 0.2 * re * np.sign(x)) / (0.09 * re)) * gauss((y - ey - 0.2 * re) / (0.09 * re))
        fc = fc + glint * (colour_logits((0.97, 0.97, 0.97)) - fc)
        return PartFields(r2, ((z - ez) / re) ** 2, fc, 0.0, window=(rows, cols))

    # -- ears -------------------------------------------------------------------------------------
    @property
    def ear_back(self) -> float:
        """Depth of the back edge of the ears."""
        return self.zc - 0.03 - 0.024 * self.p.ear_size

    def ears(self) -> PartFields:
        """Thin upright discs standing out from the sides of the skull, tilted back a little."""
        p, y, z = self.p, self.y, self.z
        es = p.ear_size
        ey = self.ey - 0.03
        ex = float(self.head_width(ey)) + 0.003
        hy = 0.040 * es
        dz = 0.024 * es
        ez = self.zc - 0.03
        A = ((self.ax - ex) / 0.012) ** 2 + ((y - ey) / hy) ** 2
        B = ((z - ez) / dz) ** 2 - 0.18 * smoothstep(ex, ex + 0.02, self.ax) * (z - ez) / dz
        inner = np.exp(-(((y - ey) / (0.6 * hy)) ** 2))
        fc = self.skin + (0.15 - 0.5 * inner).astype(np.float32) + tint(0.15, -0.05, -0.05)
        gc = (-0.6 * np.exp(-(((z - ez) / (0.6 * dz)) ** 2))).astype(np.float32)
        return PartFields(A, B, fc.astype(np.float32), gc)

    # -- torso ------------------------------------------------------------------------------------
    def _torso_fields(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Neck widening into shoulders: ``A`` over (x, y), and per column the depth centre and radius."""
        p = self.p
        H = p.head_height
        y_sh = self.yc - H - 0.085  # shoulder line
        wn = 0.48 * p.head_width
        wt = wn + (0.42 - wn) * smoothstep(y_sh + 0.04, y_sh - 0.12, y)
        y_top = self.yc - 0.45 * H  # the neck ends inside the head
        A = (x / wt) ** 2 + np.where(y > y_top, ((y - y_top) / 0.04) ** 2, 0.0)
        ax = np.abs(x)
        zt = self.zc - 0.05 - 0.02 * smoothstep(0.05, 0.25, ax)
        dt = 0.062 + 0.075 * smoothstep(0.04, 0.2, ax)
        return A, zt, dt

    def torso_front(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Depth of the neck's and shoulders' front surface over (x, y) (zc where there is none)."""
        A, zt, dt = self._torso_fields(x, y)
        return np.where(A < 1.0, zt + dt * np.sqrt(np.maximum(0.0, 1.0 - A)), self.zc)

    def torso(self) -> PartFields:
        p, x, y, z = self.p, self.x, self.y, self.z
        H = p.head_height
        A, zt, dt = self._torso_fields(x, y)
        neckline = self.yc - H - 0.105 + 3.0 * x * x
        shirt = smoothstep(neckline + 0.004, neckline - 0.004, y)
        chin_shadow = smoothstep(self.yc - 0.7 * H, self.yc - 1.0 * H - 0.03, y)
        neck = self.skin - (0.9 * (1.0 - chin_shadow)).astype(np.float32)
        fc = neck + shirt * (colour_logits(p.cloth_rgb) - neck) + (p.light_x * x).astype(np.float32)
        gc = (5.0 * (z - self.zc)).astype(np.float32)
        return PartFields(A, ((z - zt) / dt) ** 2, fc.astype(np.float32), gc)

    # -- background -------------------------------------------------------------------------------
    def background(self) -> PartFields:
        """Outside an elliptic cylinder about the y axis whose front lies beyond the box: a bowl behind
        the head that wraps round the sides, so oblique views still end on a surface."""
        p, x, y, z = self.p, self.x, self.y, self.z
        rho = np.sqrt((x / 0.44) ** 2 + ((z - 0.3) / 0.75) ** 2)
        B = np.maximum(0.0, 1.0 + (1.0 - rho) * 12.0)
        c1 = colour_logits(p.background_rgb)
        c2 = colour_logits(np.asarray(p.background_rgb) * (1.0 - p.pattern_contrast))
        k = 2.0 * np.pi * p.pattern_scale
        pattern = p.background_pattern
        if pattern == "plain":
            m = np.full((1, 1), 0.15)
        elif pattern == "gradient":
            m = smoothstep(-0.4, 0.4, y)
        elif pattern == "stripes":
            m = smoothstep(-0.3, 0.3, np.sin(k * (x + 0.3 * y)))
        elif pattern == "checker":
            m = smoothstep(-0.2, 0.2, np.sin(k * x) * np.sin(k * y))
        elif pattern == "dots":
            m = smoothstep(0.5, 0.7, np.cos(k * x) * np.cos(k * y))
        else:
            m = 0.5 + 0.5 * np.sin(k * y + 3.0 * np.sin(3.0 * np.pi * x))
        fc = c1 + m.astype(np.float32) * (c2 - c1)
        gc = (-1.2 * np.abs(x) + 0.0 * z).astype(np.float32)  # darker toward the sides
        return PartFields(0.0, B, fc.astype(np.float32), gc)

    # -- hair -------------------------------------------------------------------------------------
    def hair(self) -> PartFields:
        """Hair as a depth interval per front-view pixel.

        With ``B(z) = ((z - zh) / dzf)^2`` in front of ``zh`` and ``((z - zh) / dzb)^2`` behind it, and
        ``A = 1 - s(x, y)^2``, the hair at (x, y) spans ``zh - dzb s < z < zh + dzf s``. ``zh`` sits
        just behind the skull, so any ``s`` in [0, 1] covers the back of the head, while the front
        either lies just in front of the (grown) skull (``s_cover``: crown, forehead, curtains) or well
        behind the face (``s_hidden``). A cover mask picks between the two; a silhouette ends it.
        """
        p, x, y, z = self.p, self.x, self.y, self.z
        W, H, D = p.head_width, p.head_height, p.head_depth
        yc, zc = self.yc, self.zc
        L = p.hair_length
        st = HAIRSTYLE_SHAPES[p.hairstyle]
        t = (y - yc) / H
        ax = self.ax
        th = st.thickness * (0.75 + 0.5 * L)
        zh = zc - 1.03 * D - 0.012  # just behind the skull: any s >= 0 covers the back of the head
        dzb = 0.35 * D + 0.6 * th
        # Silhouette (front view): the skull outline grown by th (delta > 0 inside), or for the afro an
        # ellipse centred above the head; then a hanging part, the nape and a bun.
        if st.round:
            u, v = x / (W + th), (y - yc - 0.35 * H) / (0.95 * H + th)
            delta = 1.0 - np.sqrt(u * u + v * v)
        else:
            u, v = x / (self.head_width(y) + th), (y - yc) / (H + th)
            delta = 1.0 - np.sqrt(u * u + np.maximum(v, 0.0) ** 2)
        if st.hang is not None:
            hang_w = W + th + st.flare * np.maximum(yc - y, 0.0)
            y_end = yc - H - st.hang * (0.6 + 0.8 * L) - 0.03 * (1.0 - (x / hang_w) ** 2)
            hang = np.minimum(np.minimum(1.0 - ax / hang_w, (y - y_end) / 0.04), (yc - y) / 0.02)
            delta = np.maximum(delta, hang)
        delta = np.minimum(delta, (t - st.nape) * H / 0.03)
        # Round the outline over half the thickness, outside the skull: a wider rounding would pull the
        # front back to zh over the skull, leaving it thinly (or not) covered.
        edge = np.sqrt(np.clip(delta / (0.5 * th / (W + th)), 0.0, 1.0))
        # Reference depths: the front of the skull (or, below the chin, of the neck), and the front of
        # the skull grown by th in every direction (so covering hair is th thick on the sides too).
        q = np.sqrt(np.maximum(0.0, 1.0 - self.skull_A(x, y)))
        neck = self.torso_front(x, y)
        z_front = np.maximum(zc + D * q, neck)
        grown = self.skull_A(x * (W / (W + th)), yc + (y - yc) * (H / (H + th)))
        z_cover = np.maximum(zc + (D + th) * np.sqrt(np.maximum(0.0, 1.0 - grown)), neck + th)
        # Front radius per column: just enough for the deepest cover there. Smaller radii make the field
        # steeper in z, so the colour gate ends closer to the hair's hidden front.
        dzf = np.max(z_cover, axis=0, keepdims=True) + 0.005 - zh
        s_cover = np.clip((z_cover - zh) / dzf, 0.0, 1.0)
        # Hidden fronts stay well behind the face: the field is soft there (small s), so the hair's
        # colour gate reaches a few centimetres past it.
        s_hidden = np.clip((z_front - 0.07 - zh) / dzf, 0.0, 0.4)
        # Cover mask: the forehead above a hairline that drops toward the temples; curtains on the sides.
        ux = ax / W
        t_hl = st.hairline - st.temple_drop * ux * ux
        cover = smoothstep(t_hl - 0.03, t_hl + 0.02, t)
        if st.curtain_to is not None:
            face_w = np.maximum(self.head_width(y) * np.sqrt(np.maximum(0.0, 1.0 - t * t)), 1e-3)
            curtain = smoothstep(st.curtain_from, st.curtain_from + 0.08, ax / face_w)
            cover = np.maximum(cover, curtain * smoothstep(st.curtain_to - 0.15, st.curtain_to, t))
        s = edge * (cover * s_cover + (1.0 - cover) * s_hidden)
        if st.ears_visible:
            # Beside the ears only the back of the head keeps hair: the front there stops just behind
            # the ear (a cap on s, not a factor, so the field stays steep where it crosses the skin).
            ear = gauss((ax - W) / 0.03) * gauss((y - self.ey + 0.03) / 0.05)
            s_ear = (self.ear_back - 0.03 - zh) / dzf
            s = s - ear * np.maximum(s - s_ear, 0.0)
        if st.bun:
            rb = 0.042 + 0.02 * L
            yb = yc + H + th + 0.6 * rb
            bun = 1.0 - ((x / rb) ** 2 + ((y - yb) / rb) ** 2)
            s = np.maximum(s, 0.4 * np.sqrt(np.clip(bun, 0.0, 1.0)))
            delta = np.maximum(delta, bun)
        A = 1.0 - s * s + self.geometry.hair_wall * np.maximum(-delta, 0.0)
        B = (np.maximum(z - zh, 0.0) / dzf) ** 2 + (np.maximum(zh - z, 0.0) / dzb) ** 2
        # Colour: strands (or curls) over (x, y) and (x, z), a sheen band on the crown, darker below.
        if p.hairstyle == "bald":
            # A thin scalp of skin, lit as the head.
            fc = self.skin + (0.25 * p.light_x * x / W + 0.9 * (y - yc))
            gc = 0.8 * (z - zc) / D - 0.2
            return PartFields(A, B, fc, gc)
        tex, tex_xz = (
            (self.tex.curls, self.tex.curls_xz) if st.curly else (self.tex.strands, self.tex.strands_xz)
        )
        shine = 0.8 * (1.0 - 0.5 * self.hair_lightness) * gauss((t - 0.75) / 0.12)
        parting = 1.2 * gauss(x / 0.004) * smoothstep(0.5, 0.7, t) if st.parting else 0.0
        fc = self.hair_logit + (0.3 * tex + (shine - parting + 1.2 * (y - yc)))
        gc = tex_xz + 0.6 * (z - zc) / D
        return PartFields(A, B, fc, gc)

    # -- glasses and beard -------------------------------------------------------------------------
    def glasses(self) -> PartFields:
        """Two rims, a bridge and a bar out to the temples in one thin slab in front of the eyes
        (front view: rims and bars; top view: the slab), then arms running back to the ears, bending
        out around the skull (front view: the bars; top view: the arm curves)."""
        p, z = self.p, self.z
        re, ex, ey = p.eye_size, p.eye_spacing, self.ey
        zg = self.face_z(ex, ey) + 0.018
        R = 1.6 * re
        w, wz = self.geometry.glasses_wire, self.geometry.glasses_depth  # half thickness: across, along
        head_w = float(self.head_width(ey))
        hinge_x, arm_x = 0.92 * head_w, head_w + 0.007
        rows, cols = self.window(-arm_x - 2 * w, arm_x + 2 * w, ey - 1.3 * R, ey + 1.3 * R)
        x, y = self.x[:, cols], self.y[rows, :]
        ax = np.abs(x)
        rims = ((np.sqrt((ax - ex) ** 2 + ((y - ey) * 1.2) ** 2) - R) / w) ** 2
        bar = ((y - ey - 0.35 * re) / w) ** 2
        bridge = np.where(ax < ex - R + 0.002, bar, EMPTY_FIELD)
        bars = np.where((ax > ex + R - 0.002) & (ax < arm_x + w), bar, EMPTY_FIELD)
        A = np.minimum(np.minimum(rims, bridge), bars)
        front = np.where(self.ax < hinge_x + w, ((z - zg) / wz) ** 2, EMPTY_FIELD)
        z_ear = self.zc - 0.04
        curve_x = hinge_x + (arm_x - hinge_x) * smoothstep(zg, zg - 0.07, z)
        arm = ((self.ax - curve_x) / w) ** 2 + (
            np.maximum(z - zg, 0.0) ** 2 + np.maximum(z_ear - z, 0.0) ** 2
        ) / w**2
        B = np.minimum(np.minimum(front, arm), EMPTY_FIELD)
        fc = np.broadcast_to(colour_logits(p.glasses_rgb), (3, *A.shape))
        return PartFields(np.minimum(A, EMPTY_FIELD), B, fc, 0.0, window=(rows, cols))

    def beard(self) -> PartFields:
        """A layer th thick over the jaw, chin and upper lip: the skull grown by th, kept where a
        front-view mask says beard (below a line from the sideburns to the mouth, the mouth left
        open), with a short back radius so the layer never reaches the back of the head."""
        p, z = self.p, self.z
        W, H, D = p.head_width, p.head_height, p.head_depth
        yc, zc, ym = self.yc, self.zc, self.mouth_y
        th = 0.008 + 0.008 * p.hair_length
        rows, cols = self.window(-W - th - 0.01, W + th + 0.01, yc - H - th - 0.06, self.ey)
        x, y = self.x[:, cols], self.y[rows, :]
        grown = self.skull_A(x * (W / (W + th)), yc + (y - yc) * (H / (H + th)))
        line = ym + 0.018 + (self.ey - 0.03 - ym - 0.018) * (np.abs(x) / W) ** 3  # up to the sideburns
        edge = self.geometry.beard_edge
        mask = smoothstep(line + edge, line - edge, y)
        mouth = smoothstep(1.0, 0.7, (x / 0.03) ** 2 + ((y - ym) / 0.012) ** 2)
        A = grown + 3.0 * (1.0 - mask * (1.0 - mouth))
        dz = z - zc
        B = np.where(dz > 0, (dz / (D + th)) ** 2, (dz / (0.5 * D)) ** 2)
        fc = self.hair_logit + (0.35 * self.tex.stubble[rows, cols] - 0.2 + 0.25 * p.light_x * x / W)
        gc = (0.6 * dz / D).astype(np.float32)
        return PartFields(A, B, fc, gc, window=(rows, cols))
