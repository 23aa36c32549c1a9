"""Pictures of a run from its arrays: PNG files for a report, drawn with matplotlib off screen.

`write_plots(folder, arrays, series)` draws, from the arrays of result.npz (`ptrack.pipeline.run.result_arrays`)
and the per-frame metric series of `compute_metrics` ({name: (T,)}), what the run has of:

    errors.png              MPJPE (mm) over time where there is ground truth; reprojection error (px) over time
    joint_angles.png        the hips', knees', shoulders' and elbows' angles over time (degrees)
    uncertainty.png         per-joint 3D standard deviation over time (mm; `joint_std`, method batch)
    hypothesis_weights.png  the trackers' hypothesis weights per frame, sorted (`hypothesis_weights`)
    skeleton.png            5-6 snapshots of the 3D skeleton, seen from the camera and from above, over the
                            ground truth where there is one

Each picture is drawn on its own: one that fails is logged as a warning and the others are still written.
`evaluation_figure` draws `ptrack evaluate`'s table as a bar chart (results.png).

The world is Y up (the mocap's, and the model frame of a footage run); the camera is OpenCV's (x right, y
down, z forward), `camera_K/R/t` mapping world points to pixels. matplotlib is imported on first use, and only
its object-oriented API (no pyplot, no global state): importing this module costs nothing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

DPI = 100
#: the dofs of joint_angles.png: panel title -> (left joint, right joint); a dof is "<joint>.<rx|ry|rz>"
MAIN_JOINTS = {
    "hips": ("lfemur", "rfemur"),
    "knees": ("ltibia", "rtibia"),
    "shoulders": ("lhumerus", "rhumerus"),
    "elbows": ("lradius", "rradius"),
}
AXIS_COLORS = {"rx": "tab:blue", "ry": "tab:orange", "rz": "tab:green"}
LEFT, RIGHT, CENTRE, TRUTH = "tab:blue", "tab:red", "0.15", "0.72"  # skeleton colours
SNAPSHOTS = 6

Arrays = Mapping[str, np.ndarray]
Picture = Callable[[Arrays, Mapping[str, np.ndarray]], "Figure | None"]


def write_plots(folder: str | Path, arrays: Arrays, series: Mapping[str, np.ndarray] | None = None) -> list[Path]:
    """Draw the run's pictures (module docstring) into `folder` (made if missing) -> the files written.

    arrays: result.npz's arrays (times (T,), q (T, D), dof_names (D,), joints (T, J, 3), parents (J,), camera_K/R/t,
    and where the run has them gt_joints, joint_std (T, J), hypothesis_weights (T, N)); series: per-frame metrics
    {name: (T,)} (mpjpe_mm, pa_mpjpe_mm, best_of_k_mpjpe_mm, reprojection_error_px)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    series = series or {}
    written = []
    for name, draw in PICTURES.items():
        try:
            fig = draw(arrays, series)
            if fig is None:  # the run has nothing for this picture
                continue
            save(fig, folder / name)
            written.append(folder / name)
        except Exception as e:  # a picture never fails the run
            log.warning("plot %s not written: %s: %s", name, type(e).__name__, e)
    return written


def save(fig: Figure, path: str | Path) -> None:
    """Write `fig` as a PNG at DPI (zlib level 1: a third of the time of the default level, files ~20% larger)."""
    fig.savefig(path, dpi=DPI, pil_kwargs={"compress_level": 1})


def _figure(width: float, height: float) -> Figure:
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height))


def _few_ticks(*axes: Axes, count: int = 5) -> None:
    """At most `count` ticks on each axis (tick labels are most of a small figure's drawing time)."""
    from matplotlib.ticker import MaxNLocator

    for ax in axes:
        ax.xaxis.set_major_locator(MaxNLocator(count))
        ax.yaxis.set_major_locator(MaxNLocator(count))


def _margins(
    fig: Figure,
    top: float,
    bottom: float,
    left: float = 0.8,
    right: float = 0.25,
    hspace: float = 0.0,
    wspace: float = 0.2,
) -> None:
    """Fixed margins in inches (matplotlib's automatic layouts cost more than the drawing of a small figure)."""
    w, h = fig.get_figwidth(), fig.get_figheight()
    fig.subplots_adjust(
        left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h, hspace=hspace, wspace=wspace
    )


def _times(arrays: Arrays) -> np.ndarray:
    return np.asarray(arrays["times"], dtype=np.float64)


def errors_figure(arrays: Arrays, series: Mapping[str, np.ndarray]) -> Figure | None:
    """MPJPE variants (mm) over time where there is ground truth, and the reprojection error (px) over time."""
    t = _times(arrays)
    mm = [(k, label) for k, label in MM_SERIES if k in series and np.isfinite(series[k]).any()]
    px = "reprojection_error_px" in series and np.isfinite(series["reprojection_error_px"]).any()
    if not mm and not px:
        return None
    fig = _figure(8, 5.5 if mm and px else 3.2)
    _margins(fig, top=0.5, bottom=0.55, hspace=0.35 if mm and px else 0.0)
    axes = fig.subplots(int(bool(mm)) + int(px), 1, sharex=True, squeeze=False)[:, 0]
    if mm:
        ax = axes[0]
        for k, label in mm:
            ax.plot(t, series[k], label=f"{label} (mean {np.nanmean(series[k]):.1f})", lw=1.4)
        ax.set_ylabel("error (mm)")
        ax.set_ylim(bottom=0)
        ax.set_title(f"3D error against the ground truth ({len(arrays['keypoint_names'])} keypoints)", y=1.0)
        ax.legend(fontsize=8, loc="upper right")
        ax.grid(alpha=0.3)
    if px:
        ax = axes[-1]
        v = series["reprojection_error_px"]
        ax.plot(t, v, color="tab:purple", lw=1.4, label=f"mean {np.nanmean(v):.2f} px")
        ax.set_ylabel("reprojection error (px)")
        ax.set_ylim(bottom=0)
        ax.set_title("reprojection error: the estimate's keypoints to the observed ones", y=1.0)
        ax.legend(fontsize=8, loc="upper right")
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    _few_ticks(*axes)
    return fig


#: (series key, legend label) of errors.png's 3D panel
MM_SERIES = (
    ("mpjpe_mm", "MPJPE, root-aligned"),
    ("pa_mpjpe_mm", "PA-MPJPE"),
    ("best_of_k_mpjpe_mm", "best of K hypotheses"),
)


def joint_angles_figure(arrays: Arrays, series: Mapping[str, np.ndarray]) -> Figure | None:
    """The main joints' angles (MAIN_JOINTS) over time, degrees: left solid, right dashed, one colour per axis."""
    names = [str(n) for n in arrays["dof_names"]]
    q = np.degrees(np.asarray(arrays["q"], dtype=np.float64))
    panels = []
    for title, (left, right) in MAIN_JOINTS.items():
        dofs = [
            (side, n) for side, joint in (("left", left), ("right", right)) for n in names if n.startswith(joint + ".")
        ]
        if dofs:
            panels.append((title, dofs))
    if not panels:
        return None
    t = _times(arrays)
    cols = 2 if len(panels) > 1 else 1
    rows = -(-len(panels) // cols)
    fig = _figure(5 * cols, 2.6 * rows + 1.2)
    _margins(fig, top=1.0, bottom=0.55, hspace=0.45, wspace=0.22)
    axes = fig.subplots(rows, cols, sharex=True, squeeze=False).reshape(-1)
    for ax, (title, dofs) in zip(axes, panels):
        for side, n in dofs:
            axis = n.rsplit(".", 1)[1]
            ax.plot(t, q[:, names.index(n)], color=AXIS_COLORS.get(axis, "0.3"), ls=SIDE_STYLES[side], lw=1.3)
        ax.set_title(f"{title}: " + ", ".join(sorted({n.split(".")[0] for _, n in dofs})), fontsize=10, y=1.0)
        ax.set_ylabel("angle (deg)")
        ax.grid(alpha=0.3)
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    for ax in axes[-cols:]:
        ax.set_xlabel("time (s)")
    _few_ticks(*axes)
    from matplotlib.lines import Line2D

    keys = [Line2D([], [], color=c, label=f"about {a[1]}") for a, c in AXIS_COLORS.items()]
    keys += [Line2D([], [], color="0.3", ls=style, label=side) for side, style in SIDE_STYLES.items()]
    fig.legend(
        handles=keys,
        loc="upper center",
        ncol=len(keys),
        fontsize=8,
        bbox_to_anchor=(0.5, 1 - 0.42 / fig.get_figheight()),
    )
    fig.suptitle("joint angles (ASF dofs: rotations about the joint's own x, y, z axes)", fontsize=11)
    return fig


SIDE_STYLES = {"left": "-", "right": "--"}


def uncertainty_figure(arrays: Arrays, series: Mapping[str, np.ndarray]) -> Figure | None:
    """Each joint's 3D standard deviation over time (mm), a joint per row."""
    if "joint_std" not in arrays:
        return None
    from matplotlib.ticker import MaxNLocator

    std = 1000 * np.asarray(arrays["joint_std"], dtype=np.float64)  # (T, J)
    names = [str(n) for n in arrays["joint_names"]]
    t = _times(arrays)
    fig = _figure(8, 1.2 + 0.17 * len(names))
    _margins(fig, top=0.4, bottom=0.55, left=1.1, right=1.6)
    ax = fig.subplots()
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    image = ax.imshow(
        std.T,
        aspect="auto",
        interpolation="nearest",
        cmap="viridis",
        extent=(t[0] - dt / 2, t[-1] + dt / 2, len(names) - 0.5, -0.5),
    )
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.set_xlabel("time (s)")
    ax.xaxis.set_major_locator(MaxNLocator(5))
    ax.set_ylabel("joint")
    ax.set_title(f"per-joint 3D standard deviation (mean {np.nanmean(std):.1f} mm)", y=1.0)
    fig.colorbar(image, ax=ax, label="standard deviation (mm)")
    return fig


def hypothesis_weights_figure(arrays: Arrays, series: Mapping[str, np.ndarray]) -> Figure | None:
    """The trackers' hypothesis weights per frame, sorted (the heaviest at the bottom), stacked to one."""
    if "hypothesis_weights" not in arrays:
        return None
    w = np.asarray(arrays["hypothesis_weights"], dtype=np.float64)  # (T, N)
    ranked = -np.sort(-np.nan_to_num(w), axis=1)
    t = _times(arrays)
    fig = _figure(8, 3.6)
    _margins(fig, top=0.6, bottom=0.55, right=0.9)
    ax = fig.subplots()
    from matplotlib import colormaps

    colors = colormaps["viridis"](np.linspace(0.0, 0.95, ranked.shape[1]))
    ax.stackplot(t, ranked.T, colors=colors, labels=[f"#{i + 1}" for i in range(ranked.shape[1])], step=None)
    ax.set_xlim(t[0], t[-1] if len(t) > 1 else t[0] + 1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("weight")
    _few_ticks(ax)
    effective = 1 / np.maximum((w**2).sum(1), 1e-12)
    ax.set_title(
        f"{w.shape[1]} hypotheses per frame, their weights sorted (heaviest at the bottom)\n"
        f"effective number of hypotheses (1 / sum of squared weights): {np.nanmean(effective):.1f} on average",
        fontsize=10,
        y=1.0,
    )
    ax.legend(fontsize=7, ncol=1, loc="center left", bbox_to_anchor=(1.0, 0.5), title="rank", title_fontsize=7)
    return fig


def snapshot_frames(num_frames: int, count: int = SNAPSHOTS) -> np.ndarray:
    """`count` frames spread evenly over `num_frames`, first and last included (fewer when there are fewer)."""
    return np.unique(np.linspace(0, num_frames - 1, min(count, num_frames)).round().astype(np.int64))


def skeleton_figure(arrays: Arrays, series: Mapping[str, np.ndarray]) -> Figure | None:
    """Snapshots of the skeleton side by side: a strip seen from the camera (pixels, each snapshot centred across),
    a strip seen from above (x and z about the estimate's root, metres); one scale per strip."""
    from matplotlib.ticker import MaxNLocator

    joints = np.asarray(arrays["joints"], dtype=np.float64)  # (T, J, 3)
    truth = np.asarray(arrays["gt_joints"], dtype=np.float64) if "gt_joints" in arrays else None
    parents = [int(p) for p in arrays["parents"]]
    colors = _bone_colors([str(n) for n in arrays["joint_names"]], parents)
    frames = snapshot_frames(joints.shape[0])
    t = _times(arrays)
    K, R, cam_t = (np.asarray(arrays[k], dtype=np.float64) for k in ("camera_K", "camera_R", "camera_t"))
    both = joints[frames] if truth is None else np.concatenate([joints[frames], truth[frames]], axis=1)  # (F, J', 3)
    n, J = len(frames), joints.shape[1]

    pix = _project(both, K, R, cam_t)  # (F, J', 2)
    half = 0.6 * max(float(np.nanmax(np.nanmax(pix, axis=1) - np.nanmin(pix, axis=1))), 1.0)  # the strip's scale
    v_mid = (np.nanmin(pix[..., 1]) + np.nanmax(pix[..., 1])) / 2
    u_mid = (np.nanmin(pix[..., 0], axis=1) + np.nanmax(pix[..., 0], axis=1)) / 2  # (F,) each snapshot centred
    shift = np.stack([u_mid - 2 * half * np.arange(n), np.zeros(n)], -1)[:, None]  # (F, 1, 2) snapshot k at 2 half k
    camera_strip = pix - shift

    root = joints[frames, :1]  # (F, 1, 3)
    above = (both - root)[..., [0, 2]]  # (F, J', 2) x, z about the root
    reach = 1.25 * max(float(np.nanmax(np.abs(above))), 0.3)
    above_strip = above + np.stack([2 * reach * np.arange(n), np.zeros(n)], -1)[:, None]
    to_camera = (-R.T @ cam_t)[None] - root[:, 0]  # (F, 3) from the root to the camera's centre

    fig = _figure(1.9 * n + 1.1, 4.9)
    _margins(fig, top=0.95, bottom=0.15, left=1.0, right=0.15, hspace=0.12)
    top, bottom = fig.subplots(2, 1)
    for ax, strip, width in ((top, camera_strip, 2 * half), (bottom, above_strip, 2 * reach)):
        if truth is not None:
            _draw(ax, strip[:, J:].reshape(-1, 2), _strip_parents(parents, n), None)
        _draw(ax, strip[:, :J].reshape(-1, 2), _strip_parents(parents, n), colors * n)
        for k in range(1, n):
            ax.axvline((k - 0.5) * width, color="0.8", lw=0.8)
        ax.set_xlim(-width / 2, (n - 0.5) * width)
        ax.set_aspect("equal")
        ax.yaxis.set_major_locator(MaxNLocator(4))
        ax.tick_params(labelsize=7)
    if "keypoints_observed" in arrays:  # what the camera saw: the observed keypoints, shifted as their snapshot
        seen = np.asarray(arrays["confidence"])[frames] > 0  # (F, K)
        kp = np.asarray(arrays["keypoints_observed"], dtype=np.float64)[frames]  # (F, K, 2)
        observed = (kp - shift)[seen]
        top.scatter(observed[:, 0], observed[:, 1], s=7, c="k", marker="o", linewidths=0, zorder=3)
    top.set_ylim(v_mid + half, v_mid - half)  # image rows grow downwards
    top.set_xticks(2 * half * np.arange(n), [f"t = {t[f]:.2f} s" for f in frames], fontsize=8)
    top.xaxis.tick_top()
    top.tick_params(axis="x", length=0)
    bottom.set_ylim(reach, -reach)  # seen from above (Y up): x to the right, z downwards
    bottom.set_xticks([])
    for k in range(n):  # an arrow at each snapshot's edge pointing at the camera
        d = to_camera[k, [0, 2]]
        if np.linalg.norm(d) > 0:
            d = reach * d / np.linalg.norm(d)
            centre = np.array([2 * reach * k, 0.0])
            bottom.annotate(
                "",
                xy=centre + 0.97 * d,
                xytext=centre + 0.75 * d,
                arrowprops={"arrowstyle": "->", "color": "0.45", "lw": 1.2},
            )
    top.set_ylabel("from the camera\nv (px)", fontsize=9)
    bottom.set_ylabel("from above\nz about the root (m)", fontsize=9)
    what = "estimate (left blue, right red) over the ground truth (grey)" if truth is not None else "estimate"
    fig.suptitle(
        f"3D skeleton: {what}\nfrom the camera: the observed keypoints as dots, each snapshot centred across; "
        "from above: x to the right, the arrow points at the camera",
        fontsize=9,
    )
    return fig


def _strip_parents(parents: list[int], n: int) -> list[int]:
    """The parents of `n` skeletons stacked (n * J joints), each pointing into its own skeleton."""
    J = len(parents)
    return [p + k * J if p >= 0 else -1 for k in range(n) for p in parents]


def _project(points: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World points (..., 3) -> pixels (..., 2) of the camera K (3, 3), R (3, 3), t (3,); NaN behind it."""
    cam = points @ R.T + t
    z = cam[..., 2:3]
    uv = (cam @ K.T)[..., :2] / np.where(z > 1e-6, z, np.nan)
    return uv


def _bone_colors(names: list[str], parents: list[int]) -> list[str]:
    """Each joint's bone colour: LEFT for a left joint whose right mirror exists (lfemur/rfemur, lm_l_eye/lm_r_eye),
    RIGHT for its mirror, CENTRE for the others (lowerback has no "rowerback")."""
    known = set(names)

    def side(n: str) -> str:
        for a, b, color in (("l", "r", LEFT), ("r", "l", RIGHT)):
            if n.startswith(a) and b + n[1:] in known:
                return color
            if f"_{a}_" in n and n.replace(f"_{a}_", f"_{b}_", 1) in known:
                return color
        return CENTRE

    return [side(n) for n in names]


def _draw(ax: Axes, points: np.ndarray, parents: list[int], colors: list[str] | None) -> None:
    """The bones (parent, joint) of one pose, points (J, 2); colors None: the ground truth, grey and wider."""
    from matplotlib.collections import LineCollection

    segs = [(points[p], points[j]) for j, p in enumerate(parents) if p >= 0]
    bone_colors = [TRUTH] * len(segs) if colors is None else [colors[j] for j, p in enumerate(parents) if p >= 0]
    ax.add_collection(LineCollection(segs, colors=bone_colors, linewidths=3.2 if colors is None else 1.6))


PICTURES: dict[str, Picture] = {
    "errors.png": errors_figure,
    "joint_angles.png": joint_angles_figure,
    "uncertainty.png": uncertainty_figure,
    "hypothesis_weights.png": hypothesis_weights_figure,
    "skeleton.png": skeleton_figure,
}


def evaluation_figure(
    rows: list[tuple[str, dict | str]], title: str, spread: Mapping[str, float] | None = None
) -> Figure:
    """`ptrack evaluate`'s table as bars: MPJPE (mm) per clip (or, without ground truth, the reprojection error),
    the mean over the clips that ran as a dashed line, a failed clip marked. rows: (clip, metrics or the failure's
    message); spread: clip -> standard deviation over seeds, drawn as error bars."""
    key, unit = next(
        (
            (k, u)
            for k, u in (("mpjpe_mm", "MPJPE (mm)"), ("reprojection_error_px", "reprojection error (px)"))
            if any(isinstance(m, dict) and m.get(k) is not None for _, m in rows)
        ),
        ("mpjpe_mm", "MPJPE (mm)"),
    )
    names = [name for name, _ in rows]
    values = np.array(
        [float(m[key]) if isinstance(m, dict) and m.get(key) is not None else np.nan for _, m in rows], dtype=np.float64
    )
    fig = _figure(max(4.5, 0.55 * len(rows) + 2.0), 4.4)
    _margins(fig, top=0.55, bottom=0.45 + 0.05 * max(len(n) for n in names), left=0.75)
    ax = fig.subplots()
    x = np.arange(len(rows))
    err = None if spread is None else [spread.get(n, 0.0) for n in names]
    ax.bar(x, np.nan_to_num(values), yerr=err, color="tab:blue", capsize=3)
    ok = np.isfinite(values)
    if ok.any():
        mean = float(values[ok].mean())
        ax.axhline(mean, color="tab:red", ls="--", lw=1.2, label=f"mean {mean:.1f} ({int(ok.sum())} clips)")
        ax.legend(fontsize=8, loc="upper left")
    for i in np.flatnonzero(~ok):
        ax.text(float(i), 0, "failed", rotation=90, ha="center", va="bottom", fontsize=8, color="tab:red")
    ax.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
    ax.set_xlabel("clip")
    ax.set_ylabel(unit)
    ax.set_title(title + ("\nerror bars: standard deviation over the seeds" if spread else ""), fontsize=10, y=1.0)
    ax.grid(axis="y", alpha=0.3)
    return fig
