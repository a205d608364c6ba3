"""Least-squares matching: each match's point in image B moved to where image A's patch lands.

Why: on the indoor benchmark the pose error is limited by where the matched points lie, not by
how many there are: moving the correct matches toward their exact ground-truth positions lifts
AUC@10, adding correct matches from a second detector does not (docs/benchmarks.md, "Least-squares
matching: where the points lie"). Keypoint detectors place a point
to about a pixel; photogrammetry's classic answer is least-squares matching (Gruen 1985): fit
an affine warp with a radiometric gain and offset so that B's patch reproduces A's patch, by
Gauss-Newton. Image A's point is kept (it is the track's observation); only B's point moves.

A warp starts from the affine map of the match's neighbours (a weighted least-squares fit of the
other matches around it), which carries the perspective foreshortening of wide baselines that an
identity start cannot reach. A refined point is kept only when it converged inside
``max_shift`` px of where it started and the warped patch correlates with A's (NCC >=
``min_ncc``); otherwise the match keeps its original point.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class SubpixelOptions:
    radius: int = 10  # patch half-size, px at network input (21 x 21 samples)
    sigma: float = 0.7  # Gaussian pre-smoothing, px
    iterations: int = 15
    # px: a point stops iterating once it moves less (or has left max_shift); 0: every point runs
    # all iterations, the setting the matcher's refinement is tuned with
    tolerance: float = 0.0
    max_shift: float = 3.0  # px a point may move; farther means it converged elsewhere
    min_ncc: float = 0.8
    neighbour_radius: float = 40.0  # px scale of the neighbours' weights for the initial affine
    min_neighbours: int = 6  # fewer: start from the identity


def _gray(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """(1, 3, H, W) in [0, 1] -> (H, W) smoothed luminance."""
    g = image[0].float().mean(0)
    if sigma <= 0:
        return g
    r = max(1, int(3 * sigma + 0.5))
    x = torch.arange(-r, r + 1, device=g.device, dtype=g.dtype)
    k = torch.exp(-(x**2) / (2 * sigma**2))
    k = k / k.sum()
    g = F.conv2d(g[None, None], k.view(1, 1, 1, -1), padding=(0, r))
    return F.conv2d(g, k.view(1, 1, -1, 1), padding=(r, 0))[0, 0]


def _sample(maps: torch.Tensor, pts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear samples of (C, H, W) maps at (N, P, 2) pixel positions -> (C, N, P) and a mask of
    the positions inside the image."""
    _, h, w = maps.shape
    gx = pts[..., 0] * (2.0 / max(w - 1, 1)) - 1
    gy = pts[..., 1] * (2.0 / max(h - 1, 1)) - 1
    v = F.grid_sample(maps[None], torch.stack([gx, gy], -1)[None], mode="bilinear", align_corners=True)[0]
    inside = (pts[..., 0] >= 0) & (pts[..., 0] <= w - 1) & (pts[..., 1] >= 0) & (pts[..., 1] <= h - 1)
    return v, inside


def neighbour_affine(
    pa: torch.Tensor,
    pb: torch.Tensor,
    opts: SubpixelOptions,
    around: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> torch.Tensor:
    """(N, 2, 2) local linear map from A to B around each match, from the matches ``around`` it
    (default: the matches themselves; Gaussian weights); the identity where fewer than
    ``min_neighbours`` are near."""
    n = pa.shape[0]
    eye = torch.eye(2, device=pa.device).expand(n, 2, 2).clone()
    ra, rb = around if around is not None else (pa, pb)
    if ra.shape[0] < opts.min_neighbours:
        return eye
    out = eye
    chunk = 1024  # rows of the (chunk, N) weight matrix at a time: bounded memory
    ones = torch.ones(ra.shape[0], 1, device=pa.device)
    for s in range(0, n, chunk):
        da = ra[None] - pa[s : s + chunk, None]  # (c, N, 2)
        db = rb[None] - pb[s : s + chunk, None]
        d2 = (da**2).sum(-1)
        w = torch.exp(-d2 / opts.neighbour_radius**2)
        w = torch.where(d2 < (2.5 * opts.neighbour_radius) ** 2, w, torch.zeros_like(w))
        x = torch.cat([da, ones.expand_as(da[..., :1])], -1)  # (c, N, 3): offset and a free shift
        xw = x * w[..., None]
        m = xw.transpose(1, 2) @ x + 1e-6 * torch.eye(3, device=pa.device)
        sol, info = torch.linalg.solve_ex(m, xw.transpose(1, 2) @ db)  # (c, 3, 2)
        # too few near, or all on a line (a singular fit): start from the identity
        enough = ((w > 0.05).sum(1) >= opts.min_neighbours) & (info == 0) & torch.isfinite(sol).all(2).all(1)
        lin = torch.nan_to_num(sol[:, :2].transpose(1, 2))
        sv = torch.linalg.svdvals(lin)  # a fit from nearly collinear neighbours can be extreme
        enough = enough & (sv[:, 1] > 0.25) & (sv[:, 0] < 4.0)
        out[s : s + chunk] = torch.where(enough[:, None, None], lin, eye[s : s + chunk])
    return out


def refine_points(
    image_a: torch.Tensor,
    image_b: torch.Tensor,
    pa: torch.Tensor,
    pb: torch.Tensor,
    opts: SubpixelOptions | None = None,
    around: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(refined B points, mask of the refined ones) for matches ``pa`` -> ``pb`` (pixels, centres at
    integers) between two (1, C, H, W) images in [0, 1]. ``around``: the matches whose local affine
    map starts each warp (default: ``pa`` -> ``pb`` themselves)."""
    opts = opts or SubpixelOptions()
    return refine_on_maps(
        _gray(image_a, opts.sigma), gradient_maps(_gray(image_b, opts.sigma)), pa, pb, opts, around
    )


def gradient_maps(gray: torch.Tensor) -> torch.Tensor:
    """(3, H, W): a smoothed (H, W) luminance and its x and y gradients, what B is sampled from."""
    gy, gx = torch.gradient(gray)
    return torch.stack([gray, gx, gy])


def refine_on_maps(
    ga: torch.Tensor,
    maps_b: torch.Tensor,
    pa: torch.Tensor,
    pb: torch.Tensor,
    opts: SubpixelOptions,
    around: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``refine_points`` on images already smoothed (``opts.sigma`` is not applied again): A's (H, W)
    luminance and B's ``gradient_maps``, so that a photo in many pairs is prepared once."""
    n = pa.shape[0]
    if n == 0:
        return pb, torch.zeros(0, dtype=torch.bool, device=pb.device)
    pa, pb = pa.float(), pb.float()
    o = torch.arange(-opts.radius, opts.radius + 1, device=pa.device, dtype=pa.dtype)
    grid = torch.stack(torch.meshgrid(o, o, indexing="xy"), -1).reshape(-1, 2)  # (P, 2)
    lin = neighbour_affine(pa, pb, opts, around)
    # points at a time: the (points, patch samples, 8) Jacobian stays under ~64 MB
    chunk = max(1, (1 << 21) // grid.shape[0])
    out, ok = pb.clone(), torch.zeros(n, dtype=torch.bool, device=pb.device)
    for s in range(0, n, chunk):
        sl = slice(s, s + chunk)
        out[sl], ok[sl] = _gauss_newton(ga, maps_b, grid, pa[sl], pb[sl], lin[sl].clone(), opts)
    return out, ok


def _gauss_newton(
    ga: torch.Tensor,
    maps_b: torch.Tensor,
    grid: torch.Tensor,
    pa: torch.Tensor,
    pb: torch.Tensor,
    lin: torch.Tensor,
    opts: SubpixelOptions,
) -> tuple[torch.Tensor, torch.Tensor]:
    n = pa.shape[0]
    tmpl, inside_a = _sample(ga[None], pa[:, None] + grid[None])
    tmpl = tmpl[0] - tmpl[0].mean(1, keepdim=True)
    t = pb.clone()
    gain = torch.ones(n, device=pa.device)
    bias = torch.zeros(n, device=pa.device)
    eye8 = torch.eye(8, device=pa.device)
    solved = torch.ones(n, dtype=torch.bool, device=pa.device)
    # with a ``tolerance``, a point stops iterating once its step is below it (or it has left
    # ``max_shift``, which rejects it): most converge in a few steps, and computing only the moving
    # ones halves the work
    act = torch.arange(n, device=pa.device)
    gx_, gy_ = grid[:, 0], grid[:, 1]
    for _ in range(opts.iterations):
        if not len(act):
            break
        la, ga_, ba = lin[act], gain[act], bias[act]
        pts = t[act][:, None] + torch.einsum("nij,pj->npi", la, grid)
        (val, ix, iy), inside = _sample(maps_b, pts)
        res = ga_[:, None] * val + ba[:, None] - tmpl[act]
        gix, giy = ga_[:, None] * ix, ga_[:, None] * iy
        parts = [gix, giy, gix * gx_, gix * gy_, giy * gx_, giy * gy_, val, torch.ones_like(val)]
        jac = torch.stack(parts, -1)  # (N, P, 8): shift, linear map, gain, offset
        jw = (jac * (inside & inside_a[act])[..., None].float()).transpose(1, 2)
        normal = jw @ jac
        damping = 1e-4 * normal.diagonal(dim1=1, dim2=2).mean(1)[:, None, None] + 1e-6
        step, info = torch.linalg.solve_ex(normal + damping * eye8, jw @ res[..., None])
        ok_step = solved[act] & (info == 0)
        solved[act] = ok_step
        step = torch.where(ok_step[:, None], torch.nan_to_num(step[..., 0]), torch.zeros_like(step[..., 0]))
        t[act] = t[act] - step[:, :2]
        lin[act] = la - step[:, 2:6].reshape(-1, 2, 2)
        gain[act] = ga_ - step[:, 6]
        bias[act] = ba - step[:, 7]
        if opts.tolerance > 0:
            moving = step[:, :2].abs().max(1).values >= opts.tolerance
            near = (t[act] - pb[act]).norm(dim=1) <= opts.max_shift  # farther is rejected anyway
            act = act[ok_step & moving & near]
    pts = t[:, None] + torch.einsum("nij,pj->npi", lin, grid)
    (val,), inside = _sample(maps_b[:1], pts)
    vc = val - val.mean(1, keepdim=True)
    ncc = (vc * tmpl).sum(1) / (vc.norm(dim=1) * tmpl.norm(dim=1) + 1e-9)
    ok = (
        solved
        & torch.isfinite(t).all(1)
        & ((t - pb).norm(dim=1) <= opts.max_shift)
        & (ncc >= opts.min_ncc)
        & inside.all(1)
        & inside_a.all(1)
    )
    return torch.where(ok[:, None], t, pb), ok
