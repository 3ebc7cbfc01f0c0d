"""Why ``loss.render.sigma_schedule`` exists: free meshes fitted to a mask through the soft
silhouette come out smaller than the mask when drawn hard (as usl-eval draws them) with a wide
sigma, and about its size with a sharp one. The target is pyrender's mask, at 4x and averaged."""
import numpy as np
import torch
import torch.nn.functional as F
import trimesh

from render_oracle import render_pyrender
from usl.geometry import ico_sphere
from usl.render import SoftRasterSettings, rasterize_hard, rasterize_soft

SIZE = 64
K = np.array([[80.0, 0.0, 32.0], [0.0, 80.0, 32.0], [0.0, 0.0, 1.0]])
DEPTH = 3.0


def pyrender_coverage() -> torch.Tensor:
    """(SIZE, SIZE) fraction of each pixel a tilted box covers: pyrender at 4x, averaged."""
    box = trimesh.creation.box((1.6, 1.0, 1.2))
    box.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0, 1, 0]) @ trimesh.transformations.rotation_matrix(0.3, [1, 0, 0]))
    box.apply_translation([0.0, 0.0, DEPTH])
    fine = K * np.array([[4.0], [4.0], [1.0]])
    _, _, masks = render_pyrender([box], np.eye(4), fine, 4 * SIZE, 4 * SIZE)
    return F.avg_pool2d(torch.from_numpy(masks[0]).float()[None, None], 4)[0, 0]


def fitted_hard_mask(target: torch.Tensor, sigma: float, steps: int = 250) -> torch.Tensor:
    """Free ico-sphere vertices fitted with l_xent's BCE; their hard silhouette."""
    sphere, faces = ico_sphere(2)
    shift = torch.tensor([0.0, 0.0, DEPTH])
    window = torch.zeros(len(faces), dtype=torch.long)
    Kt = torch.tensor(K, dtype=torch.float32)
    settings = SoftRasterSettings(sigma=sigma, blur_radius=9.21e-3)
    verts = (0.6 * sphere).clone().requires_grad_(True)
    optimizer = torch.optim.Adam([verts], lr=0.01)
    edges = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    for _ in range(steps):
        soft = rasterize_soft(verts + shift, faces, window, Kt[None], SIZE, SIZE, settings)[0]
        edge = (verts[edges[:, 0]] - verts[edges[:, 1]]).square().sum(1).mean()
        loss = F.binary_cross_entropy(soft, target) + 0.1 * edge
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return rasterize_hard((verts + shift).detach(), faces, window, Kt, SIZE, SIZE).masks[0]


def test_a_wide_sigma_fits_hard_silhouettes_smaller_than_the_mask():
    target = pyrender_coverage()
    truth = target > 0.5
    for sigma, low, high in ((1e-3, 0.80, 0.92), (1e-4, 0.95, 1.03)):
        hard = fitted_hard_mask(target, sigma)
        area_ratio = float(hard.sum() / truth.sum())
        assert low < area_ratio < high, (sigma, area_ratio)
        assert float((hard & truth).sum() / (hard | truth).sum()) > low - 0.02, sigma
