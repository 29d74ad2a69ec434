"""Where a fit starts: empty space, or the visual hull of the refraction masks filled with the
index and grown by the offset of lowest loss (for a level set, also smoothed, tightened or
hollowed; for a voxel grid, also graded from its surface inwards); a hash grid starts as
that level set, distilled into it, or for a graded medium as a voxel grid's start.
"""

from __future__ import annotations

import numpy as np

from .. import start_losses
from ..errors import ClrefractError
from ..log import Progress
from .config import to_toml
from .distil import fit_to_field
from .kinds import KINDS, POLYTOPE_ROUNDINGS, guide_config, make_field
from .rays import Tag


class NoObject(ClrefractError):
    """The refraction masks agree on no object (a faint gas): nothing for a surface to start
    from."""


# the start search's candidates: a level set's coarse offsets (cells) searched jointly with
# the index, then line searches (index step, offset step in cells) of LINE_TRIES each; a
# voxel grid's offsets (half cells) with a full index search each, then VOXEL_FINE indices
LEVELSET_OFFSETS = (-6.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.0)
LINE_ROUNDS = ((0, 0.5), (0.25, 0), (0, 0.125), (0.08, 0))
LINE_TRIES = (-3.0, -2.0, -1.0, 1.0, 2.0, 3.0)
VOXEL_OFFSETS = (-3.0, -2.0, -1.0, 1.0)
VOXEL_FINE = 7
# a voxel grid also tries the hull graded from its surface to its deepest point by these
# powers (hull.GradedHull; the solid hull is the limit), each with a full index search:
# a graded medium's index falls to 1 at its edge, and the solid hull (shrunk 2.4 mm)
# started the quick Luneburg lens at 25.12 dB and the GRIN rod at 26.59, which their fits
# took to 26.72 and 27.85; graded by 2 they start at 27.99 and 28.78 and end at 28.25 and
# 29.21 (ceilings 29.76 and 31.61)
GRADED_POWERS = (1.0, 2.0, 4.0)
# depths (cells) of the shells a level set's start tries, each at offset 0 over the coarse
# indices; the best of them is searched as the other shapes are, from its pick
SHELL_CELLS = (2.0, 4.0, 6.0)
# a level set's coarse grids (offset x index, and the shells') rank candidates on this share
# of the batch's rays, the same rays for each, but on no fewer than COARSE_RAYS: their
# losses differ far more than 2,048 rays move them (on the quick protocol's sphere, drop,
# prism, cylinder and random solid the start picked is the one the whole batch of 8,192
# picks), where 256 rays of a 24-pixel sphere picked another
COARSE_SHARE = 4
COARSE_RAYS = 2048


def search_losses(indices: int, smoothings: list[int], shells: int = 0) -> int:
    """Losses the start search evaluates at most, over `indices` coarse indices and, for a
    level set, the smoothings of each shape (`smoothings`; none: a voxel grid's search) and
    `shells` shells."""
    if not smoothings:
        graded = (indices + VOXEL_FINE) * len(GRADED_POWERS)
        return indices * (1 + len(VOXEL_OFFSETS)) + 2 * VOXEL_FINE + graded
    lines = len(LINE_ROUNDS) * len(LINE_TRIES)
    shell = shells * indices + 1 + lines if shells else 0
    return shell + sum(
        len(LEVELSET_OFFSETS) * indices + 1 + lines + (n - 1) * (1 + lines) for n in smoothings
    )


def coarse_rays(batch: int) -> int:
    """How many of a batch's rays a coarse grid's candidate is traced on."""
    return max(batch // COARSE_SHARE, min(batch, COARSE_RAYS))


class Hulls:
    """The training views' visual hulls, by the fit's hull rule, kept for the last grid."""

    def __init__(self, ds, cfg, rays):
        self.ds, self.cfg, self.rays = ds, cfg, rays
        self._kept: dict = {}

    def at(self, box, res: int):
        if res not in self._kept:
            self._kept = {res: self.visual(box, res)}
        return self._kept[res]

    def visual(self, box, res: int):
        """The visual hull on res^3 nodes over box."""
        from ..hull import visual_hull

        return visual_hull(
            box,
            self.ds.train,
            self.rays.masks(),
            res,
            tolerance=self.cfg.hull_tolerance,
            carve=self.cfg.hull_carve,
        )

    def object_box(self):
        """The box around the visual hull that a surface needs: its margin (where the
        window brings eta to 1) and a band of the interface width beyond the hull. Rays fly
        straight to it, and its grid spends every node near the object."""
        from ..fields.base import Box

        box = self.ds.box
        hull = self.visual(box, 48)
        if not hull.found:
            raise NoObject(
                f"{self.ds.root}: the refraction masks do not agree on an object (a faint "
                "medium such as gas?); a surface model needs one: use --field voxel"
            )
        inside = np.argwhere(hull.distance > -hull.width)
        ax = [np.linspace(box.lo[a], box.hi[a], 48) for a in range(3)]
        lo = np.array([ax[a][inside[:, a].min()] for a in range(3)])
        hi = np.array([ax[a][inside[:, a].max()] for a in range(3)])
        pad = 2 * box.margin + 2 * self.cfg.width + hull.width
        lo = np.maximum(lo - pad, box.lo)
        hi = np.minimum(hi + pad, box.hi)
        return Box(tuple(lo.tolist()), tuple(hi.tolist()), box.margin)


class EmptyStart:
    """eta = 1 everywhere."""

    def run(self, fit, res: int) -> None:
        fit.bind(fit.make_field(res))


class VoxelHullStart:
    """A voxel grid with the hull filled, solid or graded; eta changes near the hull alone
    (free_cells)."""

    def run(self, fit, res: int) -> None:
        fit.bind(fit.make_field(res))
        HullSearch(fit, fit.bound, levelset=False).fill()


class LevelSetHullStart:
    """A level set of the hull, smoothed or tightened or hollowed, grown and filled."""

    def run(self, fit, res: int) -> None:
        fit.bind(fit.make_field(res))
        HullSearch(fit, fit.bound, levelset=True).fill()


class DistilledStart:
    """A hash grid starts as the level-set start (hull, index and offset searched the same
    way), fitted to its eta at points of the box: it starts where a level set does, as its
    output bias alone would take thousands of steps to reach glass. The level set (and the
    eta_max it was made with) is returned: a line search follows it."""

    def run(self, fit, res: int):
        cfg = guide_config(fit.cfg, fit.ds.scene.eta_range[1])
        guide = fit.guide_bound(make_field(cfg, fit.box, fit.eta_max, cfg.res), cfg)
        HullSearch(fit, guide, levelset=True).fill()
        made_with = fit.eta_max
        if not fit.cfg.eta_max:
            fit.eta_max = fit.kind.eta_top(fit.cfg, fit.init_info["eta"])
        rms = distil_start(fit, guide.field)
        fit.init_info["distilled_rms"] = rms
        fit.stream.write(f"start: hash grid fitted to the level-set start (eta RMS {rms:.4f})\n")
        fit.out.write_json("init.json", fit.init_info)
        return guide, made_with


class VoxelGuideStart:
    """A hash grid for a graded medium starts as a voxel grid does (its hull filled, free
    near it; or empty space), fitted to that grid's eta. The voxel grid (and the eta_max it
    was made with) is returned: a smoothed descent moves it, and the hash grid follows."""

    def run(self, fit, res: int):
        cfg = guide_config(fit.cfg, fit.eta_max)
        guide = fit.guide_bound(make_field(cfg, fit.box, fit.eta_max, cfg.res), cfg)
        if KINDS[cfg.field].start(cfg) != "empty":
            HullSearch(fit, guide, levelset=False).fill()
        # empty space too: a fresh grid's output holds eta about 1e-3 above 1, a gas's
        # whole contrast
        rms = distil_start(fit, guide.field)
        fit.init_info["distilled_rms"] = rms
        fit.stream.write(f"start: hash grid fitted to the voxel start (eta RMS {rms:.2g})\n")
        fit.out.write_json("init.json", fit.init_info)
        return guide, fit.eta_max


def distil_start(fit, source) -> float:
    """Bind a fresh hash grid fitted to another field (`source.eval`), in the fit's box;
    the RMS error of eta."""
    field = fit.make_field(0)
    rms = fit_to_field(
        field,
        source,
        fit.cfg.width,
        fit.cfg.distil_iterations,
        fit.cfg.seed,
        stream=fit.stream,
        device=fit.distil_device(),
    )
    fit.bind(field)
    return rms


# the angles within which a polytope start merges the hull's facets into one face, and the
# least share of the hull's area a face keeps, each pair tried; the faces of lowest loss are
# kept. A face's roof of hull facets spans a few degrees on 80 views, 30 or more on 20; a
# prism's faces lie 60 to 90 degrees apart, a cut stone's nearer. Faces under the share are
# the corners the cones cut: on the quick prism, keeping them (up to 30 more planes) left
# the start at 24.8 dB against 28.5
POLYTOPE_ANGLES = (8.0, 12.0, 18.0, 25.0, 35.0, 45.0)
POLYTOPE_MIN_SHARES = (0.01, 0.02, 0.05)
# the uniform offsets (mm, all faces at once) searched with each index, then each face's
# own offset by these steps, coarse to fine
POLYTOPE_OFFSETS = (-6.0, -5.0, -4.0, -3.0, -2.5, -2.0, -1.5, -1.0, -0.5, 0.0, 0.5)
POLYTOPE_FACE_STEPS = (0.5, 0.2, 0.1)
# with each rounding, the faces' common move out (mm) and the index's steps (of the coarse
# search's) tried: on the quick rounded cube (3 mm) the sharp faces came out 0.8 to 1.1 mm
# inside the truth at index 1.44 for 1.5
ROUNDING_SHIFTS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5)
ROUNDING_INDEX_STEPS = (0.0, 0.25, 0.5, 0.75)


class NoFaces(NoObject):
    """The visual hull's faces close no convex solid: no polytope to start from."""


class PolytopeHullStart:
    """A convex solid of flat faces: the planes of the visual hull's faces (facets.py) for
    each merge angle and share, with the index and a common offset of lowest loss; then
    each face's offset, the index, and the rounding of the edges by line searches."""

    def run(self, fit, res: int) -> None:
        hull = fit.hulls.at(fit.box, 64)
        if not hull.found:
            raise NoObject(f"{fit.ds.root}: the refraction masks do not agree on an object")
        self.fit = fit
        self.idx = fit.rays.mask_batch(Tag.START)
        self.etas = np.linspace(1.0, fit.ds.scene.eta_range[1], 9)[1:]
        loss, planes, eta, offset, angle = self._coarse(self._candidates(hull))
        planes = planes.copy()
        planes[:, 3] += offset
        self._bind(planes)
        loss, planes, eta = self._refined(planes, eta)
        rounding = fit.cfg.rounding
        if rounding < 0:  # searched: bevelled and polished edges
            loss, planes, eta, rounding = self._rounded(loss, planes, eta)
            fit.cfg.rounding = rounding  # recorded in config.toml: resume, render, eval
        self._bind(planes)
        fit.bound.set_params(np.append(planes.ravel(), eta), fit.it)
        fit.init_info = {
            "eta": eta,
            "rounding_mm": rounding,
            "faces": len(planes),
            "merge_angle_deg": angle,
            "offset_mm": offset,
            "loss": float(loss),
        }
        fit.stream.write(
            f"start: {len(planes)} faces of the visual hull (facets within {angle:g} degrees "
            f"merged), moved {offset:+.1f} mm, edges rounded {rounding:g} mm, index {eta:.3f} "
            f"(loss {loss:.4g})\n"
        )
        fit.out.write_json("init.json", fit.init_info)

    def _bind(self, planes, rounding=None) -> None:
        fit = self.fit
        fit.bind(fit.kind.make_planes(fit.cfg, fit.box, fit.eta_max, planes, rounding=rounding))

    def _loss(self, idx, planes, eta: float, offset: float = 0.0) -> float:
        """The loss of rays idx through the bound polytope, its planes moved by offset."""
        p = planes.copy()
        p[:, 3] += offset
        self.fit.bound.set_params(np.append(p.ravel(), eta), self.fit.it)
        return self.fit.objective.loss(self.fit.bound.tracer, idx)

    def _candidates(self, hull) -> list:
        """(merge angle, planes) of each distinct face set that closes a solid."""
        from ..facets import bounded, hull_surface, merged_planes

        fit = self.fit
        centre = (np.asarray(fit.box.lo) + np.asarray(fit.box.hi)) / 2
        points = hull_surface(hull.distance, fit.box)
        faces, seen = [], set()
        for angle in POLYTOPE_ANGLES:
            for share in POLYTOPE_MIN_SHARES:
                planes = merged_planes(points, centre, angle, share)
                key = planes.round(6).tobytes()
                if bounded(planes) and key not in seen:
                    seen.add(key)
                    faces.append((angle, planes))
        return faces

    def _coarse(self, faces) -> tuple:
        """(loss, planes, index, offset, angle): each face set with each coarse index and
        common offset, on the coarse share of the rays."""
        fit = self.fit
        coarse = self.idx[: coarse_rays(len(self.idx))]
        best = (np.inf, None, 1.0, 0.0, 0.0)
        bar = Progress(
            len(faces) * len(self.etas) * len(POLYTOPE_OFFSETS),
            "start",
            unit="losses",
            stream=fit.stream,
        )
        for angle, planes in faces:
            self._bind(planes)
            for e in self.etas:
                for o in POLYTOPE_OFFSETS:
                    loss = self._loss(coarse, planes, float(e), o)
                    bar.update(best=min(best[0], loss))
                    if loss < best[0]:
                        best = (loss, planes, float(e), float(o), angle)
        bar.close()
        if best[1] is None:
            raise NoFaces(
                f"{fit.ds.root}: the visual hull's faces close no convex solid; fit it with "
                "--field interface"
            )
        return best

    def _refined(self, planes, eta: float) -> tuple:
        """(loss, planes, index): each face's own offset, then a finer index."""
        loss = self._loss(self.idx, planes, eta)
        for step in POLYTOPE_FACE_STEPS:
            for j in range(len(planes)):
                for delta in step * np.array(LINE_TRIES):
                    trial = planes.copy()
                    trial[j, 3] += delta
                    t = self._loss(self.idx, trial, eta)
                    if t < loss:
                        loss, planes = t, trial
        step = self.etas[1] - self.etas[0]
        for e in eta + step * np.linspace(-0.75, 0.75, VOXEL_FINE):
            if e > 1:
                t = self._loss(self.idx, planes, float(e))
                if t < loss:
                    loss, eta = t, float(e)
        return loss, planes, eta

    def _rounded(self, loss: float, planes, eta: float) -> tuple:
        """(loss, planes, index, rounding): each rounding with the faces moved back out and
        the index raised (sharp faces stand in for rounded edges by moving in with a lower
        index), or the sharp faces as they were."""
        best = (loss, planes, eta, 0.0)
        step = self.etas[1] - self.etas[0]
        for k in POLYTOPE_ROUNDINGS[1:]:
            self._bind(planes, rounding=k)
            for o in ROUNDING_SHIFTS:
                for e in eta + step * np.array(ROUNDING_INDEX_STEPS):
                    t = self._loss(self.idx, planes, float(e), o)
                    if t < best[0]:
                        moved = planes.copy()
                        moved[:, 3] += o
                        best = (t, moved, float(e), k)
        return best


STARTS = {
    "polytope-hull": PolytopeHullStart,
    "empty": EmptyStart,
    "voxel-hull": VoxelHullStart,
    "levelset-hull": LevelSetHullStart,
    "distilled": DistilledStart,
    "voxel-guide": VoxelGuideStart,
}


class HullSearch:
    """Fill a bound field with the hull: the index and offset (a level set: and the shape
    and smoothing) of lowest loss on a fixed batch of rays through the masks."""

    def __init__(self, fit, bound, levelset: bool):
        self.fit, self.bound, self.levelset = fit, bound, levelset
        self.cfg, self.ds, self.stream = fit.cfg, fit.ds, fit.stream
        self._bar = None
        self._losses = None
        self._at = ""  # the shape and smoothing the search is at (their key)
        self._best_seen = np.inf

    def fill(self) -> None:
        """Fill the hull with the index, and grow or shrink it by the offset, that give the
        lowest loss on a fixed batch of rays through the masks (line searches). A level set
        also picks how much to smooth the hull: a visual hull from finitely many views is
        faceted (flat between the view cones), and a sharp surface shows every facet."""
        from ..hull import touches_frame

        fit = self.fit
        hull = fit.hulls.at(fit.box, self.bound.field.values.shape[0])
        rejected = [self.ds.train[v].name for v in hull.rejected]
        levelset = self.levelset
        if not hull.found:
            self.stream.write("start: no refraction mask agrees across views; eta = 1\n")
            return
        masks = fit.rays.masks()
        cut = [cam.name for cam, m in zip(self.ds.train, masks) if touches_frame(m)]
        if 2 * len(cut) > len(masks):
            self.stream.write(
                f"start: warning: the object runs off the picture in {len(cut)} of "
                f"{len(masks)} training views; where none of them sees it the hull cannot "
                "close (frame the whole object, or give a tighter --box)\n"
            )
        idx = fit.rays.mask_batch(Tag.START)
        etas = np.linspace(1.0, self.ds.scene.eta_range[1], 9)
        shapes = self._start_shapes(hull) if levelset else []
        shells = len(SHELL_CELLS) if levelset and self.cfg.shell_starts else 0
        self._bar = Progress(
            1 + search_losses(len(etas) - 1, [len(s[2]) for s in shapes], shells),
            "start",
            unit="losses",
            stream=self.stream,
        )
        self._best_seen = np.inf
        digest = start_losses.fingerprint(to_toml(self.cfg), self.ds.root, fit.out.path)
        self._losses = start_losses.StartLosses(fit.out.path, digest)
        graded = None  # the graded hull a voxel grid's start picks, if it does
        try:
            self._at = "empty"
            empty = self._loss_of(hull, idx, 1.0, 0.0)
            if levelset:
                best = (np.inf, 1.0, 0.0, 0.0, "visual", hull)
                if shells:
                    shapes.append(self._best_shell(hull, idx, etas))
                for name, shape, sigmas, pick in shapes:
                    # each shape's first smoothing searches index and offset jointly (a
                    # shell: from its pick), the others near the shape's best pick, up to
                    # the first that scores no better: more only rounds the shape more
                    near = (np.inf, pick)
                    for sigma in shape.width * sigmas:
                        self._at = f"{name}|{sigma:.9g}"
                        trial = self._search_levelset(shape.smoothed(sigma), idx, etas, near[1])
                        if trial[0] >= near[0]:
                            break
                        near = (trial[0], trial[1:3])
                        if trial[0] < best[0]:
                            best = (*trial, float(sigma), name, shape)
                loss, eta, offset, sigma, kind, hull = best
            else:
                self._at = "visual"
                loss, eta, offset = self._search_voxel(hull, idx, etas)
                sigma, kind, at = 0.0, "visual", self._at
                for power in GRADED_POWERS:
                    self._at, profile = f"graded {power:g}", hull.graded(power)
                    trial = self._search_index(profile, idx, etas, 0.0)
                    if trial[0] < loss:
                        (loss, eta), offset = trial, 0.0
                        graded, at = profile, self._at
                # the index once more, finer: a strong lens's loss has a narrow minimum in it
                self._at = at
                loss, eta = self._finer_index(graded or hull, idx, etas, offset, (loss, eta), 0.25)
        finally:
            self._losses.close()
        if self._losses.reused:
            self.stream.write(
                f"start: {self._losses.reused} losses taken up from an earlier start "
                f"({self._losses.path.name})\n"
            )
        bar, self._bar = self._bar, None
        if bar.done < bar.total:  # candidates skipped (indices at or below 1)
            bar.update(bar.total - bar.done, best=self._best_seen)
        if not loss < empty:
            loss, eta, offset, sigma, kind, graded = empty, 1.0, 0.0, 0.0, "visual", None
        hull = hull.smoothed(sigma)
        occ = hull.shell(offset).ravel()
        self._set_start(graded or hull, eta, offset)
        fit.init_info = {
            "hull_fraction": float((occ > 0.5).mean()),
            "mask_fraction": hull.mask_fraction,
            "eta": eta,
            "offset_mm": float(offset),
            "smoothing_mm": float(sigma),
            "hull": kind,
            "graded_power": graded.power if graded else 0.0,
            "loss": float(loss),
            "loss_empty": float(empty),
            "views_left_out": rejected,
            "views_cut_by_frame": cut,
        }
        if rejected:
            self.stream.write(
                f"start: {len(rejected)} of {len(self.ds.train)} views left out of the hull "
                "(their masks cut into what the others agree on)\n"
            )
        power = fit.init_info["graded_power"]
        fill = (
            f"graded from its surface by power {power:g} to eta {eta:.3f}"
            if power
            else f"filled with eta {eta:.3f}"
        )
        self.stream.write(
            f"start: {kind} hull {100 * fit.init_info['hull_fraction']:.2f}% of the box, "
            f"offset {offset:+.2f} mm, smoothed {sigma:.1f} mm, {fill} "
            f"(loss {loss:.4g}; empty {empty:.4g})\n"
        )
        fit.out.write_json("init.json", fit.init_info)

    def _start_shapes(self, hull):
        """(name, hull, smoothings in cells) the level-set start searches: the visual hull,
        and where asked the hull tightened onto the faces its views roof over."""
        shapes = [("visual", hull, np.array([0.0, 1.0, 2.0, 3.0, 4.0, 6.0]), None)]
        if self.cfg.tighten_hull:
            from ..hull_tighten import FLOW_TIMES, tighten

            masks = self.fit.rays.masks()
            tight = tighten(hull, self.fit.box, self.ds.train, masks, self.cfg.seed)
            for time, shape in zip(FLOW_TIMES, tight):
                shape = (f"tightened {time:g} mm^2", shape, np.array([0.0, 1.0, 2.0]), None)
                shapes.insert(0, shape)
        return shapes

    def _best_shell(self, hull, idx, etas):
        """The hull hollowed to the shell (SHELL_CELLS deep) whose best coarse index at
        offset 0 has the lowest loss, as a shape to search from that pick: a bowl's or a
        glass's hollow no silhouette shows, and the whole hull is then worse than air."""
        best = (np.inf, "", hull, 1.0)
        for cells in SHELL_CELLS:
            name = f"shell {cells:g} cells"
            self._at = f"{name}|0"
            shell = hull.hollowed(cells * hull.width)
            for e in etas[1:]:
                loss = self._loss_of(shell, idx, float(e), 0.0, coarse=True)
                if loss < best[0]:
                    best = (loss, name, shell, float(e))
        _, name, shell, eta = best
        return name, shell, np.array([0.0]), (eta, 0.0)

    def _loss_of(self, hull, idx, eta: float, offset: float, coarse: bool = False) -> float:
        """The loss of a candidate start, traced, or kept from an interrupted start; on
        `coarse_rays` of the rays `idx` for a coarse grid."""
        n = coarse_rays(len(idx)) if coarse else len(idx)
        key = f"{self._at}|{eta:.9g}|{offset:.9g}" + ("|coarse" if n < len(idx) else "")
        loss = self._losses.get(key)
        if loss is None:
            self._set_start(hull, eta, offset)
            loss = self.fit.objective.loss(self.bound.tracer, idx[:n])
            self._losses.put(key, loss)
        if self._bar is not None:
            self._best_seen = min(self._best_seen, loss)
            self._bar.update(best=self._best_seen)
        return loss

    def _search_voxel(self, hull, idx, etas):
        """Index, then offset with a full index search each (a visual hull is too big where
        the views cannot see in: concavities, or a prism's rays through parallel faces),
        then a finer index."""
        loss, eta = min((self._loss_of(hull, idx, e, 0.0), float(e)) for e in etas[1:])
        offset = 0.0
        for o in hull.width / 2 * np.array(VOXEL_OFFSETS):
            trial = min((self._loss_of(hull, idx, e, o), float(e)) for e in etas[1:])
            if trial[0] < loss:
                (loss, eta), offset = trial, float(o)
        return (*self._finer_index(hull, idx, etas, offset, (loss, eta)), offset)

    def _search_index(self, hull, idx, etas, offset: float):
        """(loss, index): the coarse indices, then finer ones about the best."""
        best = min((self._loss_of(hull, idx, e, offset), float(e)) for e in etas[1:])
        return self._finer_index(hull, idx, etas, offset, best)

    def _finer_index(self, hull, idx, etas, offset: float, best, scale: float = 1.0):
        """(loss, index): `best` or an index about it, VOXEL_FINE of them over 1.5 times
        `scale` of the coarse indices' step."""
        fine = best[1] + scale * (etas[1] - etas[0]) * np.linspace(-0.75, 0.75, VOXEL_FINE)
        cands = [(self._loss_of(hull, idx, e, offset), float(e)) for e in fine if e > 1]
        return min([best, *cands])

    def _search_levelset(self, hull, idx, etas, start=None):
        """A joint coarse search over index and offset (a hull too big where the views cannot
        see in, searched at offset 0, looks like a lower index), then alternating line
        searches, coarse to fine: offset, index, offset, index. A sharp surface is worth
        placing to a fraction of a cell. `start` = (index, offset) skips the coarse grid."""
        step = etas[1] - etas[0]
        if start is None:
            offsets = hull.width * np.array(LEVELSET_OFFSETS)
            _, eta, offset = min(
                (self._loss_of(hull, idx, float(e), float(o), coarse=True), float(e), float(o))
                for o in offsets
                for e in etas[1:]
            )
        else:
            eta, offset = start
        loss = self._loss_of(hull, idx, eta, offset)
        for de, do in LINE_ROUNDS:
            if do:
                cands = offset + hull.width * do * np.array(LINE_TRIES)
                for o in cands:
                    trial = self._loss_of(hull, idx, eta, float(o))
                    if trial < loss:
                        loss, offset = trial, float(o)
            else:
                for e in eta + step * de * np.array(LINE_TRIES):
                    if e > 1:
                        trial = self._loss_of(hull, idx, float(e), offset)
                        if trial < loss:
                            loss, eta = trial, float(e)
        return loss, eta, offset

    def _set_start(self, hull, eta: float, offset: float) -> None:
        """The field as the hull grown by offset mm and filled with index eta."""
        params = self.bound.params.copy()
        if self.levelset:
            phi = -np.clip(hull.distance + offset, -8 * hull.width, 8 * hull.width)
            params[:-1] = phi.ravel()
            params[-1] = eta
        else:
            params[:] = 1.0 + (eta - 1.0) * hull.shell(offset).ravel()
        self.bound.set_params(params, self.fit.it)
