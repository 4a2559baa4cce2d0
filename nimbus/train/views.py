"""Training views: validity masks and downscaled copies, checked at the boundary of training and scoring."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from nimbus.data import View
from nimbus.errors import NimbusError


def view_mask(view: View) -> np.ndarray | None:
    """The view's validity mask, bool ``(H, W)`` (True = the pixel counts), or None when every pixel counts.

    Checked here, at the boundary of training and scoring, for in-memory masks too: a mask
    of another size than the camera, or one that keeps no pixel (most likely the inverse
    convention, 0 = keep), is a :class:`NimbusError`, since training on it would silently
    learn nothing and scoring it would divide by zero.
    """
    mask = view.load_mask()
    if mask is None:
        return None
    mask = np.asarray(mask)
    size = (view.camera.height, view.camera.width)
    if mask.shape != size:
        raise NimbusError(f"the mask of view {view.name} is {'x'.join(map(str, mask.shape[::-1]))} but its camera "
                          f"is {size[1]}x{size[0]}; give a mask of the image's size (masks/<name>.png)")
    mask = mask.astype(bool)
    if not mask.any():
        raise NimbusError(f"the mask of view {view.name} keeps no pixel; masks mark the pixels to use with a "
                          "non-zero value and the pixels to ignore with 0 (invert it if it is the other way "
                          "round), or remove the view")
    return mask


def downscale_mask(mask: np.ndarray, height: int, width: int) -> np.ndarray:
    """A validity mask shrunk to ``height`` x ``width`` with the image's area averaging.

    A small pixel is valid only when every pixel it averages is valid: the shrunk image
    mixes the colours of its whole block, so a block that holds a single ignored pixel
    (a moving person, an undistortion border) would leak that pixel's colour into the loss.
    """
    m = torch.from_numpy(mask.astype(np.float32))[None, None]
    small = torch.nn.functional.interpolate(m, size=(height, width), mode="area")[0, 0]
    return (small >= 1.0 - 1e-6).numpy()


def downscaled_view(view: View, factor: int) -> View:
    """``view`` with its image shrunk ``factor`` times (area average) and its camera scaled to the new size.

    The image and the validity mask (:func:`downscale_mask`) are held in memory; depth and
    the sky mask are dropped, since their files keep the full size.  ``factor`` 1 returns
    ``view`` itself.
    """
    if factor == 1:
        return view
    img = torch.from_numpy(view.load_image()).permute(2, 0, 1)[None]  # [1, 3, H, W]
    h, w = max(img.shape[2] // factor, 1), max(img.shape[3] // factor, 1)
    small = torch.nn.functional.interpolate(img, size=(h, w), mode="area")[0].permute(1, 2, 0)
    mask = view_mask(view)
    if mask is not None:
        mask = downscale_mask(mask, h, w)
        if not mask.any():
            raise NimbusError(f"the mask of view {view.name} keeps no pixel once shrunk {factor} times "
                              "(train_downscale): a small pixel counts only when its whole block is valid; "
                              "lower train_downscale or remove the view")
    return dataclasses.replace(view, camera=view.camera.scaled(1.0 / factor, width=w, height=h),
                               image=small.contiguous().numpy(), image_path=None, depth=None, depth_path=None,
                               mask=mask, mask_path=None, sky=None, sky_path=None)
