"""Training on a window around the executed pixel (learner.train_crop_px).

The loss touches only the label's support (a few pixels around the executed one: the TPG kernel's ellipse,
at most kernel_radius_sigmas * sigma_x = 12 px by default), and V(s_{t+1}) is computed separately on the
whole next state. A fully convolutional net's output at a pixel depends only on the input within its
receptive field, so a forward + backward pass over a window that holds the support with that field around
it gives the same losses and gradients as the whole heightmap, at the window's share of the cost.

RoManNet's receptive field (common/model.py): 9x9 conv, two 4x4 stride-2 convs, 10 3x3 convs at 1/4
resolution, two 4x4 stride-2 transposed convs, 9x9 conv: 112 px, i.e. 56 px either side of an output pixel.
The window's corner is snapped to a multiple of 4, the net's total stride, so the stride-2 layers sample the
window on the whole image's grid: away from the window's edges (56 px), and wherever the window meets the
image's own edge, the window's output equals the whole image's exactly. What differs is only BatchNorm's
batch statistics in train mode, now taken over windows; the running statistics the actors act on are
estimated from the same windows, so training and acting stay consistent.

Within the window, the last 9x9 conv and the 1x1 heads come after the last BatchNorm and have stride 1: run on
a region of the features that holds the support with the conv's 4 px around it (head_region), they give the
window's values over the support exactly, so the step runs them there only (learner.head_crop).
"""

from __future__ import annotations

NET_STRIDE = 4  # the product of the two stride-2 convolutions


def crop_origin(size: tuple[int, int], row: int, col: int, crop: int) -> tuple[int, int]:
    """Top-left (row, col) of the crop x crop window that holds (row, col) as near its centre as the image
    and a corner on the net's stride grid allow. Needs crop <= both image sides and a multiple of 4."""
    h, w = size
    if crop % NET_STRIDE or not 0 < crop <= min(h, w):
        raise ValueError(f"crop {crop} must be a multiple of {NET_STRIDE} within the {h}x{w} image")
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"pixel ({row}, {col}) is outside the {h}x{w} image")

    def start(centre: int, side: int) -> int:
        s = round((centre - crop // 2) / NET_STRIDE) * NET_STRIDE
        return min(max(s, 0), (side - crop) // NET_STRIDE * NET_STRIDE)

    return start(row, h), start(col, w)


def head_region(boxes: list[tuple[int, int, int, int]], size: tuple[int, int],
                margin: int) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """The region of the nets' last features each item's head runs on (learner.head_crop): one (rows, cols)
    size for the batch and a top-left (row, col) per item, holding the item's box (r0, r1, c0, c1: first and
    last row and column of its label's support and executed pixel) with `margin` pixels either side, or the
    map's own edge, where the full map pads with zeros too. So the head's output over each box equals the
    full map's (common/model.py, GRConvNet.head)."""
    if not boxes:
        raise ValueError("head_region needs at least one box")
    h, w = size
    for r0, r1, c0, c1 in boxes:
        if not (0 <= r0 <= r1 < h and 0 <= c0 <= c1 < w):
            raise ValueError(f"box {(r0, r1, c0, c1)} is not within the {h}x{w} map")
    rh = min(h, max(r1 - r0 + 1 for r0, r1, _, _ in boxes) + 2 * margin)
    rw = min(w, max(c1 - c0 + 1 for _, _, c0, c1 in boxes) + 2 * margin)

    def start(lo: int, hi: int, extent: int, side: int) -> int:
        # centred on the box; shifted to the map's edge where it would cross it (the edge pads as the map does)
        return min(max(lo - margin - (extent - (hi - lo + 1) - 2 * margin) // 2, 0), side - extent)

    return (rh, rw), [(start(r0, r1, rh, h), start(c0, c1, rw, w)) for r0, r1, c0, c1 in boxes]
