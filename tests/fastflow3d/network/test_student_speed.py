"""The student's exact speed-ups compute what the plain formulation computes: the split head with channels_last
pseudo-images and the decoder's full-resolution layers at the cells they feed only (``fastflow3d.network.cells``)
against ZeroFlow's dense decoder and per-point concatenation (a reference written here), and training batches cut to
the network's points in the DataLoader against whole scans masked in the module; DataLoader workers run one BLAS
thread; the inexact point cap is a switch."""

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from fastflow3d.network.cells import CellSets, conv3x3_at, with_zero_row
from fastflow3d.network.contract import InputContract
from fastflow3d.network.model import FastFlow3D
from fastflow3d.network.scatter import scatter_mean
from fastflow3d.network.voxelize import Grid, pillar_ids, voxelize
from fastflow3d.training.data import NetworkCrop, init_worker
from fastflow3d.training.loss import flow_loss
from fastflow3d.training.student_module import StudentModule

RNG = np.random.default_rng(0)

SMALL = {
    "x_range": (-8.0, 8.0),
    "y_range": (-8.0, 8.0),
    "z_range": (-3.0, 3.0),
    "cell": 0.5,
    "pillar_channels": 16,
    "stage_channels": (16, 32, 64),
    "stage_blocks": (1, 2, 2),
}


def plain_forward(model: FastFlow3D, pc0, batch0, pc1, batch1, batch_size):
    """ZeroFlow's FastFlow3D forward as it was written before the speed-ups: BatchNorm on the in-grid rows of a
    masked copy, contiguous pseudo-images, the three pillar features gathered per point and concatenated."""
    grid, slots = model.grid, batch_size * model.grid.nx * model.grid.ny

    def embed(points, batch):
        features, ids, valid = voxelize(points, batch, grid, batch_size)
        h = model.embedder.linear(features)
        normed = torch.zeros_like(h)
        normed[valid] = model.embedder.norm(h[valid])
        rows = scatter_mean(torch.relu(normed), ids, slots + 1)
        image = rows[:slots].reshape(batch_size, grid.nx, grid.ny, -1).permute(0, 3, 1, 2).contiguous()
        return image, features, ids, valid

    def gather(image, ids):
        rows = image.permute(0, 2, 3, 1).reshape(-1, image.shape[1])
        return torch.cat([rows, rows.new_zeros((1, rows.shape[1]))])[ids]

    image0, features0, ids0, valid0 = embed(pc0, batch0)
    image1 = embed(pc1, batch1)[0]
    decoded = model.unet(image0, image1)
    per_point = torch.cat([gather(image0, ids0), gather(image1, ids0), gather(decoded, ids0), features0[:, 6:9]], 1)
    residual = nn.Sequential(*model.head)(per_point)
    return torch.where(valid0[:, None], residual, torch.zeros_like(residual)), valid0


def scans(seed: int):
    """Two samples per scan, points over the grid and a margin around it (some outside), plus a target flow."""
    gen = torch.Generator().manual_seed(seed)
    counts = (700, 500)
    pc0 = torch.rand(sum(counts), 3, generator=gen) * torch.tensor([20.0, 20.0, 7.0]) - torch.tensor([10, 10, 3.5])
    pc1 = pc0 + 0.05 * torch.randn(pc0.shape, generator=gen)
    batch = torch.cat([torch.full((n,), i, dtype=torch.int64) for i, n in enumerate(counts)])
    return pc0, batch, pc1, batch.clone(), 0.5 * torch.randn(pc0.shape, generator=gen)


def loss_and_gradients(model, forward, pc0, batch0, pc1, batch1, target):
    model.zero_grad(set_to_none=True)
    residual, valid = forward(model, pc0, batch0, pc1, batch1, 2)
    loss = flow_loss(residual, target, batch0, valid, 2, weighting="buckets")
    loss.backward()
    return loss.item(), {name: p.grad.clone() for name, p in model.named_parameters()}, residual.detach()


def assert_same_step(plain, fast):
    """The loss, the residual and every gradient of two ``loss_and_gradients`` results agree to float rounding."""
    assert abs(plain[0] - fast[0]) <= 1e-6 * abs(plain[0])
    torch.testing.assert_close(fast[2], plain[2], atol=2e-6, rtol=0)
    for name, gradient in plain[1].items():
        torch.testing.assert_close(fast[1][name], gradient, atol=3e-6, rtol=1e-4, msg=name)


def test_split_head_and_channels_last_match_the_plain_forward():
    torch.manual_seed(0)
    model = FastFlow3D(**SMALL).train()
    state = {key: value.clone() for key, value in model.state_dict().items()}
    pc0, batch0, pc1, batch1, target = scans(0)
    assert 0 < pillar_ids(pc0, batch0, model.grid, 2)[1].float().mean() < 1  # some points outside the grid
    plain = loss_and_gradients(model, plain_forward, pc0, batch0, pc1, batch1, target)
    model.load_state_dict(state)
    fast = loss_and_gradients(model, FastFlow3D.__call__, pc0, batch0, pc1, batch1, target)
    assert_same_step(plain, fast)
    model.eval()
    with torch.no_grad():
        torch.testing.assert_close(
            model(pc0, batch0, pc1, batch1, 2)[0],
            plain_forward(model, pc0, batch0, pc1, batch1, 2)[0],
            atol=2e-6,
            rtol=0,
        )


def test_convolutions_at_the_cells_are_the_dense_ones_there():
    """``CellSets``: the targets and their dilations (a 3 x 3 max-pool each), per sample, clipped at the grid's edges;
    ``conv3x3_at`` at a set from the next one's rows equals the dense convolution there, at the borders (zero
    padding) and between the two samples of a batch (no leak from one to the other)."""
    torch.manual_seed(0)
    nx, ny = 6, 7
    targets = torch.tensor([0, 6, 20, 41, nx * ny + 3, nx * ny + 29, 2 * nx * ny, 20])  # corners, a dump id, a repeat
    sets = CellSets(targets, 2, nx, ny, depth=2)
    occupied = torch.zeros(2 * nx * ny)
    occupied[targets[targets < 2 * nx * ny]] = 1
    image = occupied.reshape(2, 1, nx, ny)
    for k in range(3):
        assert torch.equal(sets.cells[k], torch.nonzero(image.reshape(-1)).reshape(-1)), k
        assert torch.equal(sets.rows[k][sets.cells[k]], torch.arange(len(sets.cells[k])))
        assert torch.all(sets.rows[k][-1] == len(sets.cells[k]))  # the dump id reads the zero row
        image = nn.functional.max_pool2d(image, 3, 1, 1)
    assert len(sets.cells[0]) == 6 < len(sets.cells[1]) < len(sets.cells[2]) < 2 * nx * ny
    conv = nn.Conv2d(5, 4, 3, 1, 1)
    dense_input = torch.randn(2, 5, nx, ny)
    dense = conv(dense_input).permute(0, 2, 3, 1).reshape(-1, 4)
    inputs = dense_input.permute(0, 2, 3, 1).reshape(-1, 5)[sets.cells[1]]
    at_cells = conv3x3_at(conv, with_zero_row(inputs), sets.neighbours(0))
    torch.testing.assert_close(at_cells, dense[sets.cells[0]], atol=1e-6, rtol=0)


def test_the_decoder_at_the_cells_of_sparse_scans_is_the_dense_one():
    """Scans of a few clusters (most of the grid empty, some cells at its edges): the network's flow and every
    gradient with the full-resolution layers computed where they are read equal the dense decoder's."""
    torch.manual_seed(2)
    model = FastFlow3D(**SMALL).train()
    state = {key: value.clone() for key, value in model.state_dict().items()}
    gen = torch.Generator().manual_seed(3)
    centres = torch.tensor([[-7.8, -7.8, 0.0], [7.8, 0.0, 0.0], [1.0, 2.0, 0.0], [-3.0, 7.9, 0.0]])
    pc0 = (centres[torch.randint(0, 4, (400,), generator=gen)] + 0.4 * torch.randn(400, 3, generator=gen)).clamp(
        -7.99, 7.99
    )
    batch0 = (torch.arange(400) >= 250).long()
    pc1, batch1, target = pc0 + 0.1, batch0.clone(), 0.3 * torch.randn(400, 3, generator=gen)
    sets = CellSets(pillar_ids(pc0, batch0, model.grid, 2)[0], 2, model.grid.nx, model.grid.ny, depth=3)
    assert len(sets.cells[3]) < 0.5 * 2 * model.grid.nx * model.grid.ny  # most cells are skipped
    plain = loss_and_gradients(model, plain_forward, pc0, batch0, pc1, batch1, target)
    model.load_state_dict(state)
    fast = loss_and_gradients(model, FastFlow3D.__call__, pc0, batch0, pc1, batch1, target)
    assert_same_step(plain, fast)


def test_training_on_the_network_points_only_is_the_same_step():
    """The DataLoader's crop (grid and ground) before the network against the whole scans, ground masked out."""
    torch.manual_seed(1)
    model = FastFlow3D(**SMALL).train()
    state = {key: value.clone() for key, value in model.state_dict().items()}
    pc0, batch0, pc1, batch1, target = scans(1)
    ground0, ground1 = pc0[:, 2] < -1.0, pc1[:, 2] < -1.0
    keep0, keep1 = ~ground0, ~ground1

    contract = InputContract(remove_ground=True, grid=model.grid)
    module = StudentModule(model, {"name": "distillation"}, None, None, contract, {}, ".")

    def masked(model, *_):  # the module's forward on whole scans (validation's path)
        batch = {"pc0_compensated": pc0, "batch0": batch0, "pc1": pc1, "batch1": batch1, "batch_size": 2}
        return module({**batch, "ground0": ground0, "ground1": ground1})

    whole = loss_and_gradients(model, masked, pc0, batch0, pc1, batch1, target)
    crop = NetworkCrop(contract)
    rows0 = torch.cat([crop.rows(pc0[batch0 == b], ground0[batch0 == b], RNG) + (batch0 < b).sum() for b in (0, 1)])
    rows1 = torch.cat([crop.rows(pc1[batch1 == b], ground1[batch1 == b], RNG) + (batch1 < b).sum() for b in (0, 1)])
    assert len(rows0) < keep0.sum() and len(rows1) < keep1.sum()  # the crop drops out-of-grid points too
    model.load_state_dict(state)
    cropped = loss_and_gradients(
        model, FastFlow3D.__call__, pc0[rows0], batch0[rows0], pc1[rows1], batch1[rows1], target[rows0]
    )
    assert abs(whole[0] - cropped[0]) <= 1e-6 * abs(whole[0])
    for name, gradient in whole[1].items():
        torch.testing.assert_close(cropped[1][name], gradient, atol=3e-6, rtol=1e-4, msg=name)


def test_network_crop_rows_and_point_cap():
    grid = Grid((-4.0, 4.0), (-4.0, 4.0), (-1.0, 1.0), 1.0)
    points = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, 2.0], [1.0, 1.0, 0.5], [-3.9, 3.9, -1.0]])
    ground = torch.tensor([False, False, False, True, False])
    assert NetworkCrop(InputContract(remove_ground=True, grid=grid)).rows(points, ground, RNG).tolist() == [0, 4]
    assert NetworkCrop(InputContract(remove_ground=False, grid=grid)).rows(points, ground, RNG).tolist() == [0, 3, 4]
    many = torch.rand(1000, 3) * 6 - 3
    crop = NetworkCrop(InputContract(remove_ground=False, grid=grid), max_points=100)
    capped = crop.rows(many, torch.zeros(1000, dtype=torch.bool), RNG)
    assert len(capped) == 100 and torch.all(capped[1:] > capped[:-1])
    sample = {
        "pc0": points,
        "pc0_compensated": points,
        "ground0": ground,
        "pseudo": points * 2,
        "pc1": points[:2],
        "ground1": ground[:2],
    }
    out = NetworkCrop(InputContract(remove_ground=True, grid=grid))(sample, RNG)
    assert out["network_points"] and torch.equal(out["pseudo"], points[[0, 4]] * 2) and len(out["pc1"]) == 1


class BlasThreads(Dataset):
    def __len__(self):
        return 1

    def __getitem__(self, index):
        from threadpoolctl import threadpool_info

        return max([pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"], default=1)


def test_dataloader_workers_run_one_blas_thread():
    loader = DataLoader(BlasThreads(), num_workers=1, worker_init_fn=lambda i: init_worker(i, blas_threads=1, rank=0))
    assert [int(x) for x in loader] == [1]
