"""Publication plates from the fatcross views: the designation as title, face labels, a
labelled scale bar, a caption (how the plate was made; "simulated scan" when it is) and the
licence line; PNG at true size (dpi in pHYs, the same facts in text chunks) and a one-page PDF.

Face labels are the abbreviations of Assyriological editions (obv., rev., t.e., b.e., l.e.,
r.e.); the layout is CDLI's fatcross (:func:`worker.register.fatcross.fatcross_layout`).
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from PIL.PngImagePlugin import PngInfo

from worker.recon.shading_maps import robust_scale
from worker.register.fatcross import (
    FATCROSS_VIEWS,
    RAKING_POLAR_DEG,
    FaceMaps,
    detail_curvature_per_um,
    encode_curvature,
    fatcross_layout,
    natural_colour,
    reduce_image,
    render_orthographic,
)

__all__ = [
    "DEFAULT_LICENCE",
    "FACE_LABELS",
    "PlateInfo",
    "annotated_plate",
    "fatcross_files",
    "render_px_per_mm",
    "plate_pdf_bytes",
    "plate_png_bytes",
    "scale_bar_mm",
]

FACE_LABELS = {"o": "obv.", "r": "rev.", "te": "t.e.", "be": "b.e.", "le": "l.e.", "re": "r.e."}
# No licence is claimed for a tablet whose holder stated none (the library's job passes the
# tablet's own licence and attribution: backend.licences.effective).
DEFAULT_LICENCE = "not stated by the holder"
KIND_CAPTIONS = {
    "natural": f"natural colour, lit from the upper left at {RAKING_POLAR_DEG:.0f}° from the "
    "view axis (the same light for every face)",
    "curvature": "mean curvature of the surface detail (overall shape removed): ridges light, "
    "troughs dark",
}


@dataclass(frozen=True)
class PlateInfo:
    """What a plate says about its tablet: the designation (e.g. a P-number), the licence
    line and whether the data are simulated."""

    designation: str
    licence: str = DEFAULT_LICENCE
    simulated: bool = False


@lru_cache(maxsize=16)
def _font(size_px: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    for name in ("DejaVuSans.ttf", "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"):
        try:
            return ImageFont.truetype(name, size_px)
        except OSError:
            continue
    try:
        return ImageFont.load_default(size=size_px)
    except (TypeError, AttributeError):  # Pillow without FreeType: the fixed bitmap font
        return ImageFont.load_default()


def scale_bar_mm(available_mm: float) -> int:
    """The longest of 10, 5, 2, 1 mm that fits in ``available_mm`` (1 mm if none does)."""
    for mm in (10, 5, 2, 1):
        if mm <= available_mm:
            return mm
    return 1


def _bar_label(mm: int) -> str:
    return "1 cm" if mm == 10 else f"{mm} mm"


def _caption(kind: str, info: PlateInfo) -> str:
    text = KIND_CAPTIONS.get(kind, kind)
    return f"SIMULATED SCAN, not a measurement of the object; {text}" if info.simulated else text


def _wrap(text: str, font, width_px: float) -> list[str]:
    """``text`` broken at spaces into lines no wider than ``width_px`` (a longer word alone)."""
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines: list[str] = []
    for word in text.split(" "):
        if lines and probe.textlength(f"{lines[-1]} {word}", font=font) <= width_px:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines


def annotated_plate(
    views: dict[str, np.ndarray], *, px_per_mm: float, info: PlateInfo, kind: str
) -> tuple[np.ndarray, dict[str, tuple[int, int, int, int]]]:
    """The fatcross of ``views`` (suffix → (H, W, 3) uint8 at ``px_per_mm``) on black with
    the title, face labels, scale bar, caption and licence in white; returns (image, boxes)
    with boxes (x0, y0, x1, y1) of "title", each view's label (its suffix), each view ("view_"
    + suffix), "scale", "caption" and "licence"."""
    if not (np.isfinite(px_per_mm) and px_per_mm > 0):
        raise ValueError(f"px_per_mm must be > 0, got {px_per_mm!r}")
    text_px = max(11, int(round(2.2 * px_per_mm)))
    font, title_font = _font(text_px), _font(int(round(1.4 * text_px)))
    line = int(round(1.4 * text_px))
    gap = max(int(round(1.5 * px_per_mm)), line + text_px // 3)
    at, (cross_h, cross_w) = fatcross_layout({k: v.shape[:2] for k, v in views.items()}, gap_px=gap)
    margin = gap
    title_h = int(round(1.4 * line)) + gap  # the title, then room for the top label
    bar_mm = scale_bar_mm(max(1.0, 0.8 * cross_w / px_per_mm))
    caption = _caption(kind, info)
    licence = f"Licence: {info.licence}"
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    # Caption and licence wrap to the cross (at least 60 mm); the title is never broken.
    text_w = max(cross_w, 60.0 * px_per_mm)
    caption_lines = _wrap(caption, font, text_w)
    licence_lines = _wrap(licence, font, text_w)
    widest = max(probe.textlength(t, font=font) for t in caption_lines + licence_lines)
    width = int(
        max(cross_w, widest, probe.textlength(info.designation, font=title_font)) + 2 * margin
    )
    foot_y = title_h + cross_h + gap
    height = foot_y + (2 + len(caption_lines) + len(licence_lines)) * line + margin
    canvas = np.zeros((height, width, 3), np.uint8)
    boxes: dict[str, tuple[int, int, int, int]] = {}
    for k, (y, x) in at.items():
        img = views[k]
        y0, x0 = title_h + y, margin + x
        canvas[y0 : y0 + img.shape[0], x0 : x0 + img.shape[1]] = img
        boxes[f"view_{k}"] = (x0, y0, x0 + img.shape[1], y0 + img.shape[0])
    pil = Image.fromarray(canvas)
    draw = ImageDraw.Draw(pil)
    white = (255, 255, 255)

    def text(key: str, xy: tuple[int, int], s: str, f) -> None:
        x0, y0 = xy
        found = []
        for i, part in enumerate(s.split("\n")):
            draw.text((x0, y0 + i * line), part, fill=white, font=f)
            found.append(draw.textbbox((x0, y0 + i * line), part, font=f))
        b = np.array(found)
        boxes[key] = (
            int(b[:, 0].min()),
            int(b[:, 1].min()),
            int(b[:, 2].max()),
            int(b[:, 3].max()),
        )

    text("title", (margin, margin // 2), info.designation, title_font)
    for k, (x0, y0, _, _) in ((k, boxes[f"view_{k}"]) for k in at):
        text(k, (x0, y0 - line), FACE_LABELS[k], font)
    bar_px = int(round(bar_mm * px_per_mm))
    thick = max(2, text_px // 5)
    bx, by = margin, foot_y + line // 2
    draw.rectangle([bx, by, bx + bar_px - 1, by + thick - 1], fill=white)
    for mm in range(bar_mm + 1):
        x = bx + min(bar_px - 1, int(round(mm * px_per_mm)))
        tick = thick * (2 if mm in (0, bar_mm) else 1)
        draw.line([x, by - tick, x, by], fill=white, width=1)
    text("scale_label", (bx + bar_px + text_px, by - text_px // 2), _bar_label(bar_mm), font)
    boxes["scale"] = (bx, by - 2 * thick, bx + bar_px, by + thick)
    y = foot_y + line + line // 2
    text("caption", (margin, y), "\n".join(caption_lines), font)
    y += line * len(caption_lines)
    text("licence", (margin, y), "\n".join(licence_lines), font)
    return np.asarray(pil), boxes


def _text_chunks(info: PlateInfo, *, kind: str, px_per_mm: float, bar_mm: int) -> dict:
    return {
        "Title": f"{info.designation} fatcross, {kind}",
        "Description": _caption(kind, info),
        "Copyright": info.licence,
        "Scale": f"scale bar {_bar_label(bar_mm)}; {px_per_mm:.4f} px/mm "
        f"({px_per_mm * 25.4:.1f} dpi, true size)",
        "px_per_mm": f"{px_per_mm:.4f}",
        "Simulated": "true" if info.simulated else "false",
        "Software": "Digital Hammurabi worker.register",
    }


def plate_png_bytes(
    image: np.ndarray, *, px_per_mm: float, info: PlateInfo, kind: str, bar_mm: int | None = None
) -> bytes:
    """PNG of ``image`` at true size: the dpi in pHYs, designation, caption, licence, scale and
    the simulated flag in tEXt chunks."""
    bar = bar_mm if bar_mm is not None else scale_bar_mm(0.8 * image.shape[1] / px_per_mm)
    meta = PngInfo()
    for key, value in _text_chunks(info, kind=kind, px_per_mm=px_per_mm, bar_mm=bar).items():
        try:
            value.encode("latin-1")
            meta.add_text(key, value)
        except UnicodeEncodeError:  # tEXt is Latin-1; iTXt carries UTF-8
            meta.add_itxt(key, value)
    dpi = px_per_mm * 25.4
    buf = io.BytesIO()
    Image.fromarray(np.asarray(image, np.uint8)).save(
        buf, format="PNG", pnginfo=meta, dpi=(dpi, dpi)
    )
    return buf.getvalue()


def plate_pdf_bytes(plates: list[np.ndarray], *, px_per_mm: float, info: PlateInfo) -> bytes:
    """One PDF page at true size holding ``plates`` side by side (top-aligned, 5 mm apart)."""
    if not plates:
        raise ValueError("plates: none given")
    gap = int(round(5 * px_per_mm))
    height = max(p.shape[0] for p in plates)
    width = sum(p.shape[1] for p in plates) + gap * (len(plates) - 1)
    page = np.zeros((height, width, 3), np.uint8)
    x = 0
    for p in plates:
        page[: p.shape[0], x : x + p.shape[1]] = p
        x += p.shape[1] + gap
    buf = io.BytesIO()
    Image.fromarray(page).save(
        buf,
        format="PDF",
        resolution=px_per_mm * 25.4,
        title=f"{info.designation} fatcross",
        subject=_caption("natural", info),
        author=info.licence,
        creator="Digital Hammurabi worker.register",
    )
    return buf.getvalue()


def render_px_per_mm(
    out_px_per_mm: float, pixel_sizes_um: list[float], extents_mm, *, max_pixels: int = 8_000_000
) -> float:
    """The rendering resolution: the data's (1000 / finest pixel size), never below the
    output's, and at most ``max_pixels`` for the largest view of a box of ``extents_mm``."""
    ext = sorted(float(e) for e in extents_mm)
    largest_area_mm2 = max(ext[1] * ext[2], 1e-6)
    data = 1000.0 / min(pixel_sizes_um) if pixel_sizes_um else out_px_per_mm
    budget = float(np.sqrt(max_pixels / largest_area_mm2))
    return max(out_px_per_mm, min(data, budget))


def _views_at(images: dict[str, np.ndarray], factor: float) -> dict[str, np.ndarray]:
    """Every view reduced by ``factor`` (output / render px per mm), rounding each extent the
    same way so that shared extents stay equal and the cross lines up."""
    out = {}
    for k, img in images.items():
        h, w = img.shape[:2]
        size = (max(1, int(round(w * factor))), max(1, int(round(h * factor))))
        out[k] = reduce_image(img, size)
    return out


def fatcross_files(
    vertices_mm: np.ndarray,
    triangles: np.ndarray,
    vertex_rgb8: np.ndarray,
    vertex_normals: np.ndarray,
    faces: list[FaceMaps],
    *,
    px_per_mm: float,
    name: str,
    info: PlateInfo,
) -> tuple[dict[str, bytes], dict]:
    """The plates of a registered tablet (merged mesh in the tablet frame, the scans' own maps
    in ``faces``): ``fatcross/{name}_fatcross_natural.png``, ``…_fatcross_curvature.png``,
    ``…_fatcross.pdf`` (both plates on one page) and each view alone
    (``{name}_{natural|curvature}_{o|r|te|be|le|re}.png``), all at ``px_per_mm``; returns
    (files, report entry)."""
    render_res = render_px_per_mm(
        px_per_mm,
        [f.pixel_size_um for f in faces],
        np.ptp(np.asarray(vertices_mm, float), axis=0),
    )
    natural, curvature, from_scans, inner_k = {}, {}, {}, []
    for suffix, rot in FATCROSS_VIEWS.items():
        r = render_orthographic(
            vertices_mm,
            triangles,
            vertex_rgb8,
            vertex_normals,
            rot,
            px_per_mm=render_res,
            faces=faces,
        )
        natural[suffix] = natural_colour(r)
        curvature[suffix], inner = detail_curvature_per_um(r, px_per_mm=render_res)
        inner_k.append(curvature[suffix][inner])
        hit = r["mask"].sum()
        from_scans[suffix] = round(float(r["from_scans"].sum() / hit), 3) if hit else 0.0
    # One display range for every view, so that a face with few signs does not have its
    # faint texture stretched to full contrast (and the faces can be compared).
    k_scale = robust_scale(np.concatenate(inner_k)) if inner_k else 1.0
    curvature = {k: encode_curvature(v, scale_per_um=k_scale) for k, v in curvature.items()}
    files: dict[str, bytes] = {}
    plates = []
    for kind, images in (("natural", natural), ("curvature", curvature)):
        views = _views_at(images, px_per_mm / render_res)
        for suffix, img in views.items():
            files[f"fatcross/{name}_{kind}_{suffix}.png"] = plate_png_bytes(
                img, px_per_mm=px_per_mm, info=info, kind=f"{kind}, {FACE_LABELS[suffix]}"
            )
        plate, _ = annotated_plate(views, px_per_mm=px_per_mm, info=info, kind=kind)
        files[f"fatcross/{name}_fatcross_{kind}.png"] = plate_png_bytes(
            plate, px_per_mm=px_per_mm, info=info, kind=kind
        )
        plates.append(plate)
    files[f"fatcross/{name}_fatcross.pdf"] = plate_pdf_bytes(plates, px_per_mm=px_per_mm, info=info)
    report = {
        "px_per_mm": round(px_per_mm, 4),
        "dpi": round(px_per_mm * 25.4, 1),
        "rendered_px_per_mm": round(render_res, 4),
        "curvature_display_per_mm": round(k_scale * 1000.0, 4),
        "light": {"polar_deg": RAKING_POLAR_DEG, "from": "upper left"},
        "normals_from_scans": from_scans,
        "designation": info.designation,
        "simulated": info.simulated,
    }
    return files, report
