"""Contact sheet: every frame as a thumbnail, blurred frames framed and labelled."""

from __future__ import annotations

import math

import numpy as np

MOTION_RGB = (230, 40, 40)    # frame colour of motion-blurred frames
DEFOCUS_RGB = (40, 110, 240)  # frame colour of defocused frames
NOPOSE_RGB = (120, 120, 120)  # frame colour of frames whose pose file says tracking was lost


def contact_sheet(thumbs: list[np.ndarray], labels: list[dict], *, columns: int = 0) -> np.ndarray:
    """Tile thumbnails into one RGB image; blurred frames get a coloured border and a caption.

    Parameters
    ----------
    thumbs : list of (h, w, 3) uint8 RGB, all the same size
    labels : per frame ``{"index": int, "blur": "none" | "motion" | "defocus", "strength_px": float,
        "pose_valid": bool}``
    columns : thumbnails per row; 0 = about square

    Returns
    -------
    (H, W, 3) uint8 RGB
    """
    import cv2

    n = len(thumbs)
    if n == 0:
        raise ValueError("no frames to put on a contact sheet")
    h, w = thumbs[0].shape[:2]
    cols = columns or max(1, math.ceil(math.sqrt(n * h / w)))
    rows = math.ceil(n / cols)
    pad, cap = 4, 16
    sheet = np.full((rows * (h + 2 * pad + cap), cols * (w + 2 * pad), 3), 255, np.uint8)
    for k, (img, lab) in enumerate(zip(thumbs, labels)):
        r, c = divmod(k, cols)
        y0, x0 = r * (h + 2 * pad + cap), c * (w + 2 * pad)
        kind = lab.get("blur", "none")
        border = {"motion": MOTION_RGB, "defocus": DEFOCUS_RGB}.get(kind)
        if not lab.get("pose_valid", True):
            border = NOPOSE_RGB
        if border is not None:
            sheet[y0:y0 + h + 2 * pad, x0:x0 + w + 2 * pad] = border
        sheet[y0 + pad:y0 + pad + h, x0 + pad:x0 + pad + w] = img
        text = f"{lab['index']}"
        if kind != "none":
            text += f" {kind} {lab.get('strength_px', 0.0):.1f}px"
        if not lab.get("pose_valid", True):
            text += " no pose"
        cv2.putText(sheet, text, (x0 + pad, y0 + h + 2 * pad + cap - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.38,
                    border if border is not None else (0, 0, 0), 1, cv2.LINE_AA)
    return sheet
