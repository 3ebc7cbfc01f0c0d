"""The paper's reason for l_dist (Sec. 3.4, Fig. 4): with non-overlapping silhouettes l_xent
gives no signal on layout, while l_dist pulls the object towards its true silhouette.

Soft silhouettes come from the render engineer's ``usl.render.rasterize_soft`` (the paper's
sigma = blur radius = 1e-3); the true silhouette is the exact analytic silhouette of a sphere.
"""

import torch

from usl.geometry.icosphere import ico_sphere
from usl.geometry.meshes import Meshes
from usl.geometry.sampling import sample_points_from_meshes
from usl.losses.silhouette import sample_mask_points, silhouette_bce_loss, silhouette_chamfer_loss
from usl.metrics.masks import mask_iou
from usl.render import rasterize_soft

SIZE = 64
K = torch.tensor([[64.0, 0.0, 32.0], [0.0, 64.0, 32.0], [0.0, 0.0, 1.0]])
RADIUS = 0.3
TARGET_CENTRE = torch.tensor([0.6, 0.1, 3.0])
START_CENTRE = torch.tensor([-0.6, -0.1, 3.0])


def sphere_silhouette(centre: torch.Tensor) -> torch.Tensor:
    """(H, W) bool: pixels whose centre ray passes within RADIUS of the sphere centre."""
    v, u = torch.meshgrid(torch.arange(SIZE) + 0.5, torch.arange(SIZE) + 0.5, indexing="ij")
    rays = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(K).T
    rays = rays / rays.norm(dim=-1, keepdim=True)
    along = rays @ centre
    miss2 = centre.dot(centre) - along**2
    return miss2 < RADIUS**2


def soft_silhouette(verts_cam: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    return rasterize_soft(verts_cam, faces, torch.zeros(len(faces), dtype=torch.long), K[None], SIZE, SIZE)


def xent_gradient(sphere: Meshes, faces: torch.Tensor, centre: torch.Tensor, target: torch.Tensor):
    """l_xent of the sphere at ``centre`` against ``target`` and its gradient w.r.t. the centre."""
    centre = centre.clone().requires_grad_()
    xent = silhouette_bce_loss(soft_silhouette(sphere.verts_packed() + centre, faces), target[None].float())
    (grad,) = torch.autograd.grad(xent.loss.sum(), centre)
    return xent, grad


def dist_gradient(sphere: Meshes, centre: torch.Tensor, target: torch.Tensor, gen: torch.Generator):
    centre = centre.clone().requires_grad_()
    true_points, true_lengths = sample_mask_points(target[None], 400, generator=gen)
    points = sample_points_from_meshes(sphere, 300, generator=gen) + centre
    loss = silhouette_chamfer_loss(points, K, (SIZE, SIZE), true_points, true_lengths)
    (grad,) = torch.autograd.grad(loss.sum(), centre)
    return grad


def test_l_dist_moves_a_disjoint_sphere_onto_its_silhouette_while_l_xent_is_blind_to_it():
    verts, faces = ico_sphere(2)
    sphere = Meshes.from_shared_topology(verts[None] * RADIUS, faces)
    gen = torch.Generator().manual_seed(0)
    other_centre = torch.tensor([-0.5, 0.6, 3.0])
    target, other = sphere_silhouette(TARGET_CENTRE), sphere_silhouette(other_centre)
    empty = torch.zeros_like(target)
    start = sphere_silhouette(START_CENTRE)
    assert mask_iou(start, target) == 0 and mask_iou(start, other) == 0

    # l_xent: the gate is off, and the target contributes (near) zero gradient: against
    # either disjoint target, or none at all, the gradient is the same. (Under perspective
    # it is not zero itself: it changes the sphere's projected area, whatever the target.)
    xent, grad_target = xent_gradient(sphere, faces, START_CENTRE, target)
    _, grad_other = xent_gradient(sphere, faces, START_CENTRE, other)
    _, grad_empty = xent_gradient(sphere, faces, START_CENTRE, empty)
    assert not xent.gate.item()
    assert (grad_target - grad_empty).norm() < 1e-6 * grad_empty.norm().clamp(min=1e-3)
    assert (grad_other - grad_empty).norm() < 1e-6 * grad_empty.norm().clamp(min=1e-3)

    # l_dist: the gradient points towards whichever silhouette is the target
    for centre in (TARGET_CENTRE, other_centre):
        descent = -dist_gradient(sphere, START_CENTRE, sphere_silhouette(centre), gen)[:2]
        towards = (centre - START_CENTRE)[:2]
        assert torch.nn.functional.cosine_similarity(descent, towards, dim=0) > 0.8

    # and gradient descent on the image-plane translation with l_dist alone lands the sphere
    # on it (depth stays fixed: one view cannot tell depth from size, hence multiple views)
    true_points, true_lengths = sample_mask_points(target[None], 400, generator=gen)
    translation = START_CENTRE[:2].clone().requires_grad_()
    optimizer = torch.optim.SGD([translation], lr=0.5, momentum=0.5)
    for _ in range(50):
        points = sample_points_from_meshes(sphere, 300, generator=gen) + torch.cat([translation, START_CENTRE[2:]])
        loss = silhouette_chamfer_loss(points, K, (SIZE, SIZE), true_points, true_lengths)
        optimizer.zero_grad()
        loss.sum().backward()
        optimizer.step()
    assert mask_iou(sphere_silhouette(torch.cat([translation.detach(), START_CENTRE[2:]])), target) > 0.85

    # once the silhouettes overlap, the target does shape l_xent's gradient (not vacuous)
    near = TARGET_CENTRE + torch.tensor([0.05, 0.0, 0.0])
    overlap, grad_near = xent_gradient(sphere, faces, near, target)
    _, grad_near_empty = xent_gradient(sphere, faces, near, empty)
    assert overlap.gate.item() and (grad_near - grad_near_empty).norm() > 1e-2 * grad_near_empty.norm()
