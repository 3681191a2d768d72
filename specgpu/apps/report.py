"""The report a colour scientist reads: one self-contained HTML page per run, for ``specgpu demo`` and for
``specgpu report RUN_FOLDER`` (any capture and its recovery).

What each recovery contributes is summarised once (:func:`summarise_method`: per-patch and per-pixel errors
against the truth, the dE2000 map, the predicted sigma, sRGB renderings under D65 and A, the patch spectra) and
the page (:func:`report_page`) is built from the summaries: a summary at the top, the tables (ours beside the
paper's for the demo), the recovered against the true spectrum of every patch for each method (with the
+- 1 sigma band of the noise model where a sigma map exists), error maps on one scale with their colour bars and
units, the renderings, and each plan's illuminant sequence.
"""

from __future__ import annotations

import html
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from specgpu import io
from specgpu.apps import paper
from specgpu.apps.report_figures import (
    DELTA_E_LABEL,
    SIGMA_LABEL,
    common_scale,
    figure_png,
    illuminant_figure,
    map_figure,
    rgb_jpeg,
    spectra_figure,
    sRGB_rendering,
)
from specgpu.apps.report_html import Cell, card_grid, cell, figure_card, html_table, page
from specgpu.engine.colorimetry import reflectance_to_XYZ
from specgpu.io.motion_truth import sequence_truth
from specgpu.io.paths import atomic_path
from specgpu.pipeline.capture_folder import read_capture
from specgpu.pipeline.evaluate import (
    evaluate_pixels,
    evaluate_reflectance,
    evaluate_XYZ,
    patch_means,
    scene_XYZ,
    true_patch_spectra,
)
from specgpu.pipeline.motion_record import motion_notice, moved, without_motion
from specgpu.pipeline.recovery import recover, uncertainty
from specgpu.rig.scene import colorchecker_scene, load_scene

__all__ = ["RENDER_ILLUMINANTS", "MethodSummary", "summarise_method", "report_page", "summary_table",
           "find_captures", "capture_names", "recovered_capture", "report_folder", "REPORT_MOTION"]

#: The illuminants every reflectance recovery (and the truth) is rendered under.
RENDER_ILLUMINANTS = ("D65", "A")


@dataclass
class MethodSummary:
    """What the report shows of one recovery (small: maps of (H, W), spectra of (P, B), 8-bit renderings).

    ``patch`` / ``pixels`` / ``delta_E`` are None without a truth; ``spectra`` / ``sigma_spectra`` None for an XYZ
    output or a scene without patches; ``sigma_map`` the RMS over bands of the predicted per-pixel sigma."""

    name: str
    plan: object
    XYZ: np.ndarray
    renderings: dict
    patch: object = None
    pixels: dict | None = None
    delta_E: np.ndarray | None = None
    spectra: np.ndarray | None = None
    sigma_spectra: np.ndarray | None = None
    sigma_map: np.ndarray | None = None

    @property
    def illuminant(self) -> str:
        """The illuminant of :attr:`XYZ` and of the colour differences."""
        return "D65" if self.plan.output == "reflectance" else self.plan.illuminant


def summarise_method(name, plan, y, scene=None, *, sigma=None, device=None, patch=None,
                     pixels=None) -> MethodSummary:
    """One recovery (``y``: the plan's outputs, (H, W, B)) scored against ``scene`` (None: no truth) as the demo
    and ``specgpu evaluate`` score it (reflectance under D65 on its own bands, XYZ under its plan's illuminant);
    ``sigma`` (H, W, B) the predicted per-pixel standard deviation of ``y``; ``patch`` and ``pixels``: its
    per-patch and per-pixel reports when scored so already (:func:`specgpu.apps.demo_measure.measure_methods`),
    used instead of scoring it again."""
    y = np.asarray(y, np.float32)
    reflectance = plan.output == "reflectance"
    wl = plan.output_wavelengths
    if reflectance:
        renders = {ill: reflectance_to_XYZ(y, wl, ill, device=device) for ill in RENDER_ILLUMINANTS}
        XYZ = renders["D65"]
    else:
        renders = {plan.illuminant: y}
        XYZ = y
    s = MethodSummary(name, plan, XYZ, {ill: sRGB_rendering(v, ill) for ill, v in renders.items()})
    if sigma is not None and reflectance:
        sig = np.asarray(sigma, np.float64)
        s.sigma_map = np.sqrt(np.mean(sig ** 2, axis=-1)).astype(np.float32)
    if scene is None:
        return s
    if reflectance:
        s.patch = patch if patch is not None else (
            evaluate_reflectance(y, wl, scene, illuminant="D65") if scene.masks else None)
        px = pixels if pixels is not None else evaluate_pixels(y, scene, wavelengths=wl, illuminant="D65",
                                                               device=device)
        if scene.masks:
            _, s.spectra = patch_means(y, scene.masks)
            if sigma is not None:
                _, s.sigma_spectra = patch_means(np.asarray(sigma, np.float32), scene.masks)
    else:
        s.patch = patch if patch is not None else (
            evaluate_XYZ(y, scene, illuminant=plan.illuminant) if scene.masks else None)
        px = pixels if pixels is not None else evaluate_pixels(y, scene, illuminant=plan.illuminant,
                                                               device=device)
    s.pixels, s.delta_E = px.statistics(), px.delta_E_2000
    return s


# ------------------------------------------------------------------------------------------------------- tables

def summary_table(summaries) -> str:
    """One row per method: frames, per-patch RMSE / dE*ab / dE2000 (mean and max) and per-pixel dE2000 (mean,
    95th percentile); the lowest of each error column marked."""
    columns = ["method", "frames", "RMSE patch mean", "RMSE patch max", "ΔE*ab patch mean", "ΔE*ab patch max",
               "ΔE00 patch mean", "ΔE00 patch max", "ΔE00 pixel mean", "ΔE00 pixel p95"]
    rows = []
    for s in summaries.values():
        summ = s.patch.summary() if s.patch is not None else {}
        r = summ.get("rmse", (None, None))
        ab = summ.get("delta_E_ab", (None, None))
        d00 = summ.get("delta_E_2000", (None, None))
        px = (s.pixels or {}).get("delta_E_2000", {})
        rows.append([s.name, str(s.plan.K), cell(r[0], 4), cell(r[1], 4), cell(ab[0]), cell(ab[1]), cell(d00[0]),
                     cell(d00[1]), cell(px.get("mean")), cell(px.get("p95"))])
    return html_table(columns, rows, caption="Every recovery of this run against the truth (lowest of each "
                      "error column marked)", best_columns=range(2, 10))


def patch_table_html(summaries, names) -> str:
    """Per patch, one table of each method's spectral RMSE (reflectance recoveries) and one of its dE2000, so
    that many methods still fit the page; the lowest of each column marked."""
    with_patch = [s for s in summaries.values() if s.patch is not None]
    out = []
    for key, label, digits in (("rmse", "spectral RMSE", 4), ("delta_E_2000", "ΔE00", 2)):
        rows_of = [s for s in with_patch if getattr(s.patch, key) is not None]
        if not rows_of:
            continue
        columns = ["#", "patch"] + [s.name for s in rows_of]
        rows = [[str(i + 1), name] + [cell(getattr(s.patch, key)[i], digits) for s in rows_of]
                for i, name in enumerate(names)]
        out.append(html_table(columns, rows, caption=f"Per patch: {label} of each method (lowest of each column "
                              "marked)", best_columns=range(2, len(columns)), text_columns=2))
    return "".join(out)


def table2_html(nb, sy) -> str:
    """Table 2 as HTML: per patch, narrowband (NB) and symmetric basis (SB), ours beside the paper's."""
    columns = ["#", "patch", "RMSE NB", "paper", "RMSE SB", "paper", "ΔE*ab NB", "paper", "ΔE*ab SB", "paper"]
    rows = []
    for i, name in enumerate(paper.PATCHES):
        p = paper.TABLE2[i]
        rows.append([str(i + 1), name, cell(nb.rmse[i], 4), cell(p[0], 4), cell(sy.rmse[i], 4), cell(p[1], 4),
                     cell(nb.delta_E_ab[i]), cell(p[2]), cell(sy.delta_E_ab[i]), cell(p[3])])
    rows.append(["", "average", cell(np.mean(nb.rmse), 4), cell(np.mean([p[0] for p in paper.TABLE2]), 4),
                 cell(np.mean(sy.rmse), 4), cell(np.mean([p[1] for p in paper.TABLE2]), 4),
                 cell(np.mean(nb.delta_E_ab)), cell(np.mean([p[2] for p in paper.TABLE2])),
                 cell(np.mean(sy.delta_E_ab)), cell(np.mean([p[3] for p in paper.TABLE2]))])
    return html_table(columns, rows, caption="Table 2: per patch, narrowband (NB) and symmetric basis (SB), ours "
                      "beside the paper's (lowest of each column marked)", best_columns=range(2, 10),
                      row_classes=[None] * len(paper.PATCHES) + ["paper"], text_columns=2)


def table3_html(d65, a) -> str:
    """Table 3 as HTML: the tristimulus imager's dE*ab per patch under D65 and A, ours beside the paper's."""
    columns = ["#", "patch", "ΔE*ab D65", "paper", "ΔE*ab A", "paper"]
    rows = [[str(i + 1), name, cell(d65.delta_E_ab[i]), cell(paper.TABLE3[i][0]), cell(a.delta_E_ab[i]),
             cell(paper.TABLE3[i][1])] for i, name in enumerate(paper.PATCHES)]
    sd, sa = d65.summary()["delta_E_ab"], a.summary()["delta_E_ab"]
    pd, pa = paper.TABLE3_SUMMARY["D65"], paper.TABLE3_SUMMARY["A"]
    rows.append(["", "average", cell(sd[0]), cell(pd[0]), cell(sa[0]), cell(pa[0])])
    rows.append(["", "maximum", Cell(f"{sd[1]:.2f}"), Cell(f"{pd[1]:.2f}"), Cell(f"{sa[1]:.2f}"), Cell(f"{pa[1]:.2f}")])
    return html_table(columns, rows, caption="Table 3: tristimulus imager, ΔE*ab per patch under D65 and A, ours "
                      "beside the paper's (lowest of each column marked)", best_columns=range(2, 6),
                      row_classes=[None] * len(paper.PATCHES) + ["paper", "paper"], text_columns=2)


# --------------------------------------------------------------------------------------------------- the page

def _summary_lines(summaries) -> list[str]:
    scored = [s for s in summaries.values() if s.pixels]
    lines = []
    if scored:
        best = min(scored, key=lambda s: s.pixels["delta_E_2000"]["mean"])
        lines.append(f"Lowest per-pixel ΔE00: <b>{html.escape(best.name)}</b> "
                     f"({best.pixels['delta_E_2000']['mean']:.2f} mean, {best.plan.K} frames).")
        spectral = [s for s in scored if s.patch is not None and s.patch.rmse is not None]
        if spectral:
            b = min(spectral, key=lambda s: float(np.mean(s.patch.rmse)))
            lines.append(f"Lowest per-patch spectral RMSE: <b>{html.escape(b.name)}</b> "
                         f"({float(np.mean(b.patch.rmse)):.4f} mean over {len(b.patch.names)} patches).")
        fewest = min(scored, key=lambda s: (s.plan.K, s.pixels["delta_E_2000"]["mean"]))
        lines.append(f"Fewest frames: <b>{html.escape(fewest.name)}</b> ({fewest.plan.K} frames, "
                     f"{fewest.pixels['delta_E_2000']['mean']:.2f} per-pixel ΔE00).")
    else:
        lines.append("No truth for this run: renderings and predicted uncertainty only, no errors.")
    return lines


def _spectra_section(summaries, scene, keep=None) -> str:
    spectral = [s for s in summaries.values() if s.spectra is not None]
    if not spectral or scene is None:
        return ""
    cards = []
    names, truth = true_patch_spectra(scene)
    for s in spectral:
        band = "; band: ± 1σ predicted per pixel" if s.sigma_spectra is not None else ""
        fig = spectra_figure(names, s.plan.output_wavelengths, s.spectra, scene.wavelengths, truth,
                             sigma=s.sigma_spectra,
                             title=f"{s.name} ({s.plan.K} frames): recovered (solid) vs true (broken){band}")
        png = figure_png(fig)
        if keep is not None:
            keep(f"spectra-{s.name}", png)
        cards.append(figure_card(png, f"{s.name}: patch means, recovered vs true reflectance"))
    return ("<h2>Recovered vs true spectra (the paper's Fig. 15)</h2><p>Each panel a patch: the recovery's mean "
            "over the patch against the true reflectance; the band is ± 1σ of one pixel as the noise model "
            "predicts it.</p>" + card_grid(cards, wide=True))


def _maps_section(summaries) -> str:
    out = []
    with_dE = [s for s in summaries.values() if s.delta_E is not None]
    if with_dE:
        vmax = common_scale([s.delta_E for s in with_dE])
        cards = [figure_card(figure_png(map_figure(s.delta_E, vmax=vmax, label=DELTA_E_LABEL,
                                                   title=f"{s.name}, under {s.illuminant}")),
                             f"{s.name}: ΔE00 per pixel, 0-{vmax:g}") for s in with_dE]
        out.append(f"<h2>Error maps</h2><p>CIEDE2000 per pixel against the truth, every map on one scale "
                   f"(0 to {vmax:g} ΔE00, the largest 95th percentile; higher values clip, grey: no valid "
                   f"pixel).</p>" + card_grid(cards))
    with_sigma = [s for s in summaries.values() if s.sigma_map is not None]
    if with_sigma:
        vmax = common_scale([s.sigma_map for s in with_sigma])
        cards = [figure_card(figure_png(map_figure(s.sigma_map, vmax=vmax, label=SIGMA_LABEL, cmap="viridis",
                                                   title=s.name)), f"{s.name}: predicted σ, 0-{vmax:g}")
                 for s in with_sigma]
        out.append(f"<h2>Predicted uncertainty</h2><p>The noise model's per-pixel standard deviation of the "
                   f"recovered reflectance (RMS over bands), one scale (0 to {vmax:g}).</p>" + card_grid(cards))
    return "".join(out)


def _renderings_section(summaries, scene, device) -> str:
    cards = []
    if scene is not None:
        for ill in RENDER_ILLUMINANTS:
            cards.append(figure_card(rgb_jpeg(sRGB_rendering(scene_XYZ(scene, ill, device=device), ill)),
                                     f"truth under {ill}", "image/jpeg"))
    for s in summaries.values():
        for ill, rgb in s.renderings.items():
            cards.append(figure_card(rgb_jpeg(rgb), f"{s.name} under {ill}", "image/jpeg"))
    return ("<h2>sRGB renderings</h2><p>Reflectance rendered under D65 and A (a tristimulus recovery under its "
            "own illuminant), adapted to sRGB's D65 white (CAT02), a perfect white at code 255.</p>"
            + card_grid(cards))


def _illuminants_section(summaries, bundle, keep=None) -> str:
    if bundle is None:
        return ""
    cards = []
    for s in summaries.values():
        png = figure_png(illuminant_figure(s.plan, bundle, title=f"{s.name}: {s.plan.K} illuminants"))
        if keep is not None:
            keep(f"illuminants-{s.name}", png)
        cards.append(figure_card(png, f"{s.name} illuminants: targets wide and faint, emitted dashed"))
    return ("<h2>Illuminant sequences</h2><p>Each plan's target spectra and what its quantized DMD patterns emit "
            "by the calibrated model.</p>" + card_grid(cards, wide=True))


def report_page(title: str, intro, summaries: dict, *, scene=None, bundle=None, tables: str = "",
                device=None, sections: str = "", keep=None) -> str:
    """The report as one HTML document: ``intro`` (HTML, or a callable returning it, called once every figure is
    drawn, so that a run time it states counts them) and the summary on top, then ``tables`` (HTML; the
    per-method and per-patch tables are added), ``sections`` (HTML, each with its own heading), spectra, error
    and sigma maps, renderings and illuminants. ``keep(name, png)``, when given, receives each spectra and
    illuminant figure as it is drawn (``spectra-<method>``, ``illuminants-<method>``: PNG bytes), so that a caller
    writing them as files draws each once."""
    names = next((s.patch.names for s in summaries.values() if s.patch is not None), None)
    patch = patch_table_html(summaries, names) if names and not tables else ""
    rest = (_spectra_section(summaries, scene, keep=keep) + _maps_section(summaries)
            + _renderings_section(summaries, scene, device) + _illuminants_section(summaries, bundle, keep=keep))
    summary = ("<div class='summary'>" + (intro() if callable(intro) else intro) + "<ul>"
               + "".join(f"<li>{line}</li>" for line in _summary_lines(summaries)) + "</ul>"
               + summary_table(summaries) + "</div>")
    body = (f"<h1>{html.escape(title)}</h1>{summary}"
            + (f"<h2>Tables</h2>{tables}{patch}" if tables or patch else "") + sections + rest)
    return page(title, body)


# --------------------------------------------------------------------------------------- specgpu report FOLDER

def find_captures(folder) -> dict:
    """name -> sequence folder of a run: the folder itself when it is one (named after it), else each folder
    holding a ``sequence.json`` directly inside it or inside its ``sequences/`` (the demo's layout)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a folder")
    if (folder / io.SEQUENCE_FILE).is_file():
        return {folder.name: folder}
    found = {}
    for parent in (folder / "sequences", folder):
        if parent.is_dir():
            for sub in sorted(parent.iterdir()):
                if (sub / io.SEQUENCE_FILE).is_file() and sub.name not in found:
                    found[sub.name] = sub
    if not found:
        raise ValueError(f"{folder}: no capture in it (a folder with {io.SEQUENCE_FILE}, here or in "
                         f"{folder / 'sequences'})")
    return found


def _truth_of(meta, height, width, truth):
    """The truth scene of a capture: ``truth`` when given, else the scene its metadata records (the demo's chart
    rebuilt with its white tile), None when the recorded one cannot be rebuilt (a scene from elsewhere)."""
    recorded = meta.get("metadata", {}) or {}
    if truth is not None:
        return load_scene(truth, height, width)
    name = recorded.get("scene")
    if name == "colorchecker" and recorded.get("chart"):
        return colorchecker_scene(height, width, chart=recorded["chart"], white_tile=recorded.get("white_tile"))
    try:
        return load_scene(name, height, width) if name else None
    except (ValueError, OSError):
        return None


def capture_names(plans: dict) -> dict:
    """folder name -> the name a capture goes by in the report: its plan's method (``plans``: folder name -> plan),
    with the folder's name beside it where two captures share a method."""
    methods = [p.method for p in plans.values()]
    return {name: p.method if methods.count(p.method) == 1 or name == p.method else f"{p.method} ({name})"
            for name, p in plans.items()}


#: The compensation the report decodes a capture that moved with (``specgpu recover --motion``'s mode).
REPORT_MOTION = "global"


def recovered_capture(seq, *, truth=None, device=None, say=None) -> tuple:
    """One capture as the report shows it: ``(y, sigma, scene, note)``. A still capture is the mean of its
    sequences (the white ROI its metadata records), scored against ``truth`` or the scene it records. A capture
    that moved (:func:`specgpu.pipeline.motion_record.moved`) is its first sequence decoded with motion
    compensation (``recover --motion global --sequence 0``), scored against that sequence's recorded motion truth
    unless ``truth`` is given; ``note`` (HTML-free text, also passed to ``say``) says so, None for a still one.
    One the compensation refuses (the decoder's one-line refusal) is reported as a still one, its note saying why."""
    meta = seq.meta.get("metadata", {}) or {}
    roi = meta.get("white_roi")
    noisy = seq.plan.output == "reflectance" and "noise" in seq.plan.params
    h, w = seq.frames.shape[-2:]
    if not moved(seq):
        y = recover(seq, device=device, white_roi=roi)
        sigma = uncertainty(seq, device=device, white_roi=roi)[0] if noisy else None
        return y, sigma, _truth_of(seq.meta, h, w, truth), None
    try:
        y = recover(seq, sequence=0, device=device, motion=REPORT_MOTION)
    except ValueError as why:  # a capture the compensation does not take (the decoder says why in one line)
        note = without_motion(seq, averaged=True) + f" (the report could not compensate it: {why})"
        if say is not None:
            say(note)
        y = recover(seq, device=device, white_roi=roi)
        sigma = uncertainty(seq, device=device, white_roi=roi)[0] if noisy else None
        return y, sigma, _truth_of(seq.meta, h, w, truth), note
    sigma = uncertainty(seq, sequence=0, device=device)[0] if noisy else None
    scene = load_scene(truth if truth is not None else sequence_truth(seq.path, 0), h, w)
    against = "the truth given" if truth is not None else "its recorded motion truth"
    if truth is None:  # named after the scene captured, not the truth file's name
        scene = replace(scene, name=f"{meta.get('scene') or 'a scene'} moving (its truth at sequence 0)")
    note = motion_notice(seq, f"reported as `specgpu recover --motion {REPORT_MOTION} --sequence 0` decodes it "
                              f"(sequence 0 of {seq.sequences}, motion-compensated), scored against {against}")
    if say is not None:
        say(note)
    return y, sigma, scene, note


def report_folder(folder, *, out=None, truth=None, device=None, say=None) -> Path:
    """Write the report of a run folder (one capture, or several: :func:`find_captures`) to ``out`` (default
    ``FOLDER/report.html``): each capture recovered (:func:`recovered_capture`: the mean of its sequences, or for
    a capture that moved its first sequence motion-compensated) and its sigma predicted, scored against ``truth``
    (a scene name or file; default the scene the capture records, when it can be rebuilt), named by its plan's
    method (:func:`capture_names`). ``say`` gets the one line about each capture that moved. The page states the
    whole job's run time, its figures included. Returns the path written."""
    t_start = time.perf_counter()
    folder = Path(folder)
    captures = find_captures(folder)
    out = Path(out) if out is not None else folder / "report.html"
    summaries, scene, bundle, notes = {}, None, None, []
    seqs = {name: read_capture(path) for name, path in captures.items()}
    names = capture_names({name: seq.plan for name, seq in seqs.items()})
    for name, seq in seqs.items():
        y, sigma, own, note = recovered_capture(seq, truth=truth, device=device, say=say)
        notes += [note] if note else []
        scene = scene if scene is not None else own
        bundle = bundle or seq.calibration
        summaries[names[name]] = summarise_method(names[name], seq.plan, y, own, sigma=sigma, device=device)
    first = next(iter(captures.values()))

    def intro():  # made last, once every figure is drawn: the run time counts them
        how = ("each recovered on the OpenCL device from its frames (the mean of its sequences, a capture that "
               "moved as said below) with the calibration and plan stored in it")
        return (f"<p>Run folder <code>{html.escape(str(folder))}</code>: {len(captures)} capture(s) of "
                f"{html.escape(str(scene.name) if scene is not None else 'an unknown scene')}, {how} (first: "
                f"<code>{html.escape(str(first))}</code>). Run time {time.perf_counter() - t_start:.1f} s, "
                "figures included.</p>" + "".join(f"<p class='note'>{html.escape(n)}</p>" for n in notes))

    with atomic_path(out) as tmp:
        tmp.write_text(report_page(f"specgpu report: {folder.name}", intro, summaries, scene=scene, bundle=bundle,
                                   device=device))
    return out
