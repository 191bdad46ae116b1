"""Encode-process-decode graph network simulator (Sanchez-Gonzalez et al. 2020), PyTorch.

Node features [n, 3 C + 6 + 1]: the last C normalized velocities, the distances to the six
domain faces divided by the connectivity radius R and clamped to [-1, 1], the normalized
friction angle. Edge features [E, 4]: (x_sender - x_receiver) / R and its norm. M
message-passing steps update edge latents and node latents with residuals and LayerNorm;
the decoder gives the normalized acceleration, integrated by semi-implicit Euler.

The first layer of every edge MLP is computed per node and gathered (W [e, h_s, h_r] =
W_e e + (W_s h)[s] + (W_r h)[r]): no [E, 3L] concatenation is ever formed.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import torch
from torch import nn

CHUNK_EDGES = 8192  # edges per block of the inference path ([8192, L] floats stay in cache)


@dataclass(frozen=True)
class ModelConfig:
    latent: int = 128
    mlp_layers: int = 2  # hidden layers per MLP
    message_passing: int = 10
    input_velocities: int = 5

    def to_dict(self) -> dict:
        return asdict(self)


def _mlp(n_in: int, latent: int, n_out: int, layers: int, norm: bool) -> nn.Sequential:
    mods: list[nn.Module] = []
    width = n_in
    for _ in range(layers):
        mods += [nn.Linear(width, latent), nn.ReLU()]
        width = latent
    mods.append(nn.Linear(width, n_out))
    if norm:
        mods.append(nn.LayerNorm(n_out))
    return nn.Sequential(*mods)


class _SplitFirstMLP(nn.Module):
    """MLP over the concatenation of inputs, first layer split per input (no concat)."""

    def __init__(self, widths: tuple[int, ...], latent: int, layers: int) -> None:
        super().__init__()
        self.first = nn.ModuleList(nn.Linear(w, latent, bias=i == 0) for i, w in enumerate(widths))
        self.rest = _mlp(latent, latent, latent, layers - 1, norm=True)

    def forward(self, *parts: torch.Tensor) -> torch.Tensor:  # parts already gathered
        x = self.first[0](parts[0])
        for lin, part in zip(self.first[1:], parts[1:], strict=False):
            x = x + lin(part)
        return self.rest(torch.relu(x))


class Processor(nn.Module):
    def __init__(self, latent: int, layers: int) -> None:
        super().__init__()
        self.edge = _SplitFirstMLP((latent, latent, latent), latent, layers)
        self.node = _SplitFirstMLP((latent, latent), latent, layers)

    def forward(self, h, e, senders, receivers):
        if not torch.is_grad_enabled():
            return self._forward_inference(h, e, senders, receivers)
        f = self.edge.first
        hs, hr = f[1](h), f[2](h)  # per-node halves of the first edge layer [n, L]
        pre = f[0](e) + hs.index_select(0, senders) + hr.index_select(0, receivers)
        e_new = self.edge.rest(torch.relu(pre))
        agg = torch.zeros_like(h).index_add_(0, receivers, e_new)
        h_new = self.node(h, agg)
        return h + h_new, e + e_new

    def _forward_inference(self, h, e, senders, receivers):
        """The same update without autograd, in edge chunks that stay in cache: no [E, L]
        intermediate is materialized and e is updated in place."""
        f = self.edge.first
        hs = f[1](h)
        hr = torch.addmm(f[0].bias, h, f[2].weight.T)  # the first bias, added per node
        lins = [m for m in self.edge.rest if isinstance(m, nn.Linear)]
        norm = self.edge.rest[-1]
        w0 = f[0].weight.T
        agg = torch.zeros_like(h)
        for a in range(0, e.shape[0], CHUNK_EDGES):
            part = slice(a, a + CHUNK_EDGES)
            x = torch.mm(e[part], w0)
            x += hs.index_select(0, senders[part])
            x += hr.index_select(0, receivers[part])
            x.relu_()
            for lin in lins[:-1]:
                x = torch.addmm(lin.bias, x, lin.weight.T).relu_()
            x = torch.addmm(lins[-1].bias, x, lins[-1].weight.T)
            x = nn.functional.layer_norm(x, norm.normalized_shape, norm.weight, norm.bias,
                                         norm.eps)
            e[part] += x
            agg.index_add_(0, receivers[part], x)
        return h + self.node(h, agg), e


class GNS(nn.Module):
    def __init__(self, config: ModelConfig, stats: dict) -> None:
        super().__init__()
        self.config = config
        c, L, k = config.input_velocities, config.latent, config.mlp_layers
        for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
            self.register_buffer(key, torch.tensor(stats[key], dtype=torch.float32))
        self.register_buffer("friction", torch.tensor(
            [stats["friction_mean_deg"], stats["friction_std_deg"]], dtype=torch.float32))
        self.radius = float(stats["connectivity_radius_m"])
        self.spacing = float(stats.get("particle_spacing_m", 0.0))  # m, for domain checks
        self.node_in = 3 * c + 6 + 1
        self.node_encoder = _mlp(self.node_in, L, L, k, norm=True)
        self.edge_encoder = _mlp(4, L, L, k, norm=True)
        self.processor = nn.ModuleList(Processor(L, k) for _ in range(config.message_passing))
        self.decoder = _mlp(L, L, 3, k, norm=False)

    def features(self, positions, friction_deg, bounds, senders, receivers):
        """positions [n, C+1, 3] (m), friction_deg [n], bounds [3, 2] or [n, 3, 2] (lo, hi; m)."""
        vel = (positions[:, 1:] - positions[:, :-1] - self.vel_mean) / self.vel_std
        last = positions[:, -1]
        dist = torch.cat([last - bounds[..., 0], bounds[..., 1] - last], dim=1) / self.radius
        fr = ((friction_deg - self.friction[0]) / self.friction[1]).unsqueeze(1)
        nodes = torch.cat([vel.flatten(1), dist.clamp(-1.0, 1.0), fr], dim=1)
        rel = (last.index_select(0, senders) - last.index_select(0, receivers)) / self.radius
        edges = torch.cat([rel, rel.norm(dim=1, keepdim=True)], dim=1)
        return nodes, edges

    def forward(self, positions, friction_deg, bounds, senders, receivers):
        """Normalized acceleration [n, 3] of the next frame."""
        nodes, edges = self.features(positions, friction_deg, bounds, senders, receivers)
        h, e = self.node_encoder(nodes), self.edge_encoder(edges)
        for block in self.processor:
            h, e = block(h, e, senders, receivers)
        return self.decoder(h)

    def acceleration(self, positions, friction_deg, bounds, senders, receivers):
        """Acceleration [n, 3] of the next frame, m/frame^2 (the forward pass denormalized)."""
        return self(positions, friction_deg, bounds, senders, receivers) * self.acc_std + self.acc_mean

    def next_positions(self, positions, friction_deg, bounds, senders, receivers):
        """Semi-implicit Euler: v' = v + a, x' = x + v' (per frame), [n, 3] m."""
        acc = self.acceleration(positions, friction_deg, bounds, senders, receivers)
        vel = positions[:, -1] - positions[:, -2] + acc
        return positions[:, -1] + vel


def deepen(model: GNS, stats: dict, message_passing: int) -> GNS:
    """`model` with message-passing steps appended up to `message_passing`, each new one an
    identity at first (its edge and node MLPs end in a LayerNorm of zero scale and shift, so
    their residual updates are zero): the deeper model predicts exactly what `model` does and
    training can grow its receptive field (M x R) from there."""
    have = model.config.message_passing
    if message_passing <= have:
        raise ValueError(f"deepen to {message_passing} message-passing steps: the model has "
                         f"{have} already")
    deeper = GNS(replace(model.config, message_passing=message_passing), stats)
    deeper = deeper.to(next(model.parameters()).device)
    missing, unexpected = deeper.load_state_dict(model.state_dict(), strict=False)
    assert not unexpected and all(k.startswith("processor.") for k in missing), missing
    with torch.no_grad():
        for block in deeper.processor[have:]:
            for norm in (block.edge.rest[-1], block.node.rest[-1]):
                norm.weight.zero_()
                norm.bias.zero_()
    return deeper
