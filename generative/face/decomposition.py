"""Seed 003 §3, decomposition: one LoRA adapter per intrinsic on the frozen completion backbone, with
cross-intrinsic attention; the *shared* and *independent* ablations."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from foundation.errors import CheckpointError, ForeignCheckpointError, UsageError
from foundation.loop import RunState, Stage

from generative.diffusion import ConditionalDiffusion, OptimizerStage, train_stage

from .data import FaceSet, TARGETS

#: lit (3), seen (1), covered (1), the baseline's albedo (3), position (3) and normal (3) in the face frame
from .encoding import (BRANCHES, COND_CHANNELS, MAP_CHANNELS, at_resolution, condition, decode_maps,
                       encode_albedo, encode_maps, mirror, normalise_albedo)
from .completion import FaceModelResult, data_digest, load_completion
from .settings import DecompSettings


# -- 2. decomposition: LoRA adapters per intrinsic on the frozen backbone, cross-intrinsic attention --------------


class CrossIntrinsicAttention:
    """A ``diffusers`` attention processor for self-attention over K branches stacked branch-major in the batch:
    queries stay per branch, keys and values are concatenated over the branches (seed 003 §3,
    h_i = Attn(q_i, [K_1 … K_K], [V_1 … V_K])). With ``branches = 1`` it is ordinary self-attention."""

    def __init__(self, branches: int):
        self.branches = branches

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states=None, attention_mask=None,
                 temb=None, **kwargs) -> torch.Tensor:
        if encoder_hidden_states is not None or attention_mask is not None or hidden_states.ndim != 3:
            raise UsageError("CrossIntrinsicAttention is for unmasked self-attention over (B, N, C) tokens")
        residual = hidden_states
        kb, n, _ = hidden_states.shape
        k = self.branches
        if kb % k:
            raise UsageError(f"batch {kb} is not {k} branches of equal size")
        b = kb // k
        q, key, v = attn.to_q(hidden_states), attn.to_k(hidden_states), attn.to_v(hidden_states)
        heads = attn.heads
        d = q.shape[-1] // heads

        def tokens(x):  # (K·B, N, H·D) → (B, H, K·N, D): branch k's tokens at [k·N, (k+1)·N)
            return x.view(k, b, n, heads, d).permute(1, 3, 0, 2, 4).reshape(b, heads, k * n, d)

        out = F.scaled_dot_product_attention(tokens(q), tokens(key), tokens(v))
        out = out.view(b, heads, k, n, d).permute(2, 0, 3, 1, 4).reshape(kb, n, heads * d)
        out = attn.to_out[1](attn.to_out[0](out))
        if attn.residual_connection:
            out = out + residual
        return out / attn.rescale_output_factor


#: the seed injects LoRA "into attention and feedforward projections"; conv_in too, so that each branch reads its input
#: its own way (each branch writes its map through its own head)
def torch_maps(x: torch.Tensor) -> dict[str, torch.Tensor]:
    """Encoded maps (B, 8, H, W) → (B, H, W, C) tensors in the UV shader's units (differentiable): linear albedo,
    normal-map rgb (n/2 + ½), roughness, specular."""
    x = x.permute(0, 2, 3, 1)
    a = ((x[..., :3] + 1.0) * 0.5).clamp(0.0, 1.0)
    albedo = torch.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055).clamp(min=1e-6) ** 2.4)  # sRGB decode
    n = F.normalize(x[..., 3:6], dim=-1, eps=1e-6)
    return {"albedo": albedo.contiguous(), "normal": (n * 0.5 + 0.5).contiguous(),
            "roughness": ((x[..., 6:7] + 1.0) * 0.5).clamp(0.05, 1.0).contiguous(),
            "specular": ((x[..., 7:8] + 1.0) * 0.5).clamp(0.0, 1.0).contiguous()}


def uv_shading_error(lights: list, eyes: list, ambient: list):
    """Seed 003's shading loss ‖T̂_shaded(predicted maps) − T_shaded(true maps)‖² over covered texels, through the
    UV-space GGX shader (:func:`mi_plugins.uv_shader.shade_uv`, Dr.Jit) called from torch (``dr.wrap`` in
    :mod:`foundation.bridge`). ``lights[i]``: instance i's :class:`UVLight` list; ``eyes[i]``: its camera
    position; ``ambient[i]``: I_amb (the seed samples it from U(0.15, 0.3)). Returns ``f(pred_maps, true_maps,
    position, normal, tangent, covered)`` on torch tensors."""
    import drjit as dr
    import mitsuba as mi

    from foundation.bridge import torch_to_drjit_loss
    from mi_plugins.uv_shader import UVMaps, UVView, shade_uv

    def fn(pa, pn, pr, ps, ta, tn, tr, ts, pos, nrm, tan, covered):
        total = mi.Float(0.0)
        count = 0.0
        for i in range(len(eyes)):
            def shade(a, n, r, s_):
                maps = UVMaps(albedo=a[i], normal=n[i], roughness=r[i], specular=s_[i])
                return shade_uv(pos[i], nrm[i], tan[i], maps, lights[i], UVView(position=eyes[i]), ambient=ambient[i])
            d = (shade(pa, pn, pr, ps) - shade(ta, tn, tr, ts)) * covered[i]
            total += dr.sum(d * d, axis=None)
            count += 3.0 * float(np.prod(covered[i].shape))
        return total / count

    loss = torch_to_drjit_loss(fn)

    def call(pred: dict, true: dict, pos, nrm, tan, covered):
        return loss(pred["albedo"], pred["normal"], pred["roughness"], pred["specular"], true["albedo"], true["normal"],
                    true["roughness"], true["specular"], pos, nrm, tan, covered)

    return call


LORA_TARGETS = r".*(conv_in|proj_in|proj_out|to_q|to_k|to_v|to_out\.0|ff\.net\.0\.proj|ff\.net\.2)$"


def _set_adapter_names(module, args, kwargs, names):
    kwargs["adapter_names"] = names
    return args, kwargs


#: the template defaults in the encoded space (normal (0, 0, 1), roughness 0.5, specular 0.35); the albedo branch
#: starts from its input, the completed albedo
DEFAULT_ENCODED = (0.0, 0.0, 1.0, 0.0, -0.3)


class Decomposer(nn.Module):
    """The four intrinsics from (albedo estimate, condition): one forward pass over all branches.

    Each branch reads the backbone's last feature map (its ``conv_out`` removed) and the condition through its own
    small head (two 3×3 convolutions, the last zero-initialised), added to where the branch starts: the input albedo, or the template's defaults — an untrained
    decomposition *is* the baseline. ``cross_attention`` / ``shared``: the frozen backbone with one ``peft`` LoRA
    adapter per branch (a mixed-adapter batch, branch-major); ``cross_attention`` also swaps the backbone's
    self-attention for :class:`CrossIntrinsicAttention`. ``independent``: one full copy of the backbone per branch,
    all of it trained. Outputs are in the encoded spaces of :func:`encode_maps`.
    """

    def __init__(self, backbone: ConditionalDiffusion, s: DecompSettings):
        super().__init__()
        import copy
        import warnings

        self.s = s
        self.variant = s.variant
        width = backbone.cfg.widths[0]
        torch.manual_seed(s.seed)
        self.heads = nn.ModuleList([nn.Sequential(nn.Conv2d(width + COND_CHANNELS, 32, 3, padding=1), nn.SiLU(),
                                                  nn.Conv2d(32, c, 3, padding=1)) for c in TARGETS.values()])
        for h in self.heads:
            nn.init.zeros_(h[-1].weight)
            nn.init.zeros_(h[-1].bias)
        self.register_buffer("defaults", torch.tensor(DEFAULT_ENCODED, dtype=torch.float32).view(1, -1, 1, 1))

        def trunk():
            net = copy.deepcopy(backbone)
            net.unet.conv_out = nn.Identity()  # the backbone's features, not its v-prediction
            return net

        if s.variant == "independent":
            self.nets = nn.ModuleList([trunk() for _ in BRANCHES])
            return
        from peft import LoraConfig, inject_adapter_in_model
        from peft.tuners.lora import LoraLayer

        self.net = trunk()
        for name in BRANCHES:
            # lora_dropout 0: the branches are mixed in one batch (peft's adapter_names), which peft allows at
            # inference only because dropout would differ per branch; without dropout training is the same function
            cfg = LoraConfig(r=s.rank, lora_alpha=s.rank, lora_dropout=0.0, target_modules=LORA_TARGETS,
                             init_lora_weights=True)
            with warnings.catch_warnings():  # peft warns that a second adapter joins the first: that is the design
                warnings.filterwarnings("ignore", message="Already found a `peft_config`")
                self.net.unet = inject_adapter_in_model(cfg, self.net.unet, adapter_name=name)
        for n, p in self.net.named_parameters():
            p.requires_grad_("lora_" in n)
        self.lora_layers = [m for m in self.net.unet.modules() if isinstance(m, LoraLayer)]
        if s.variant == "cross_attention":
            procs = dict(self.net.unet.attn_processors)
            for k in procs:
                if k.endswith("attn1.processor"):
                    procs[k] = CrossIntrinsicAttention(len(BRANCHES))
            self.net.unet.set_attn_processor(procs)

    def trainable(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def features(self, albedo: torch.Tensor, cond: torch.Tensor) -> list[torch.Tensor]:
        """Each branch's last feature map (B, width, H, W) of the (adapted) backbone at t = 0."""
        b = albedo.shape[0]
        k = len(BRANCHES)
        t = torch.zeros(b, dtype=torch.long)
        if self.variant == "independent":
            return [net(albedo, t, cond, net.tokens(None, b)) for net in self.nets]
        names = [n for n in BRANCHES for _ in range(b)]
        hooks = [m.register_forward_pre_hook(lambda mod, a, kw: _set_adapter_names(mod, a, kw, names), with_kwargs=True)
                 for m in self.lora_layers]
        try:
            rep = lambda x: x.repeat(k, *([1] * (x.ndim - 1)))  # noqa: E731
            y = self.net(rep(albedo), t.repeat(k), rep(cond), self.net.tokens(None, k * b))
        finally:
            for h in hooks:
                h.remove()
        return list(y.view(k, b, *y.shape[1:]))

    def forward(self, albedo: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """albedo (B, 3, H, W) encoded, cond (B, 14, H, W) → (B, 8, H, W) encoded maps."""
        f = self.features(albedo, cond)
        start = torch.cat([albedo, self.defaults.expand(albedo.shape[0], -1, *albedo.shape[2:])], 1)
        return start + torch.cat([h(torch.cat([x, cond], 1)) for h, x in zip(self.heads, f)], 1)


def decomposition_loss(pred: torch.Tensor, target: torch.Tensor, covered: torch.Tensor, weights) -> tuple[torch.Tensor, dict]:
    """Weighted mean squared error per branch over covered texels; returns the total and the per-branch terms."""
    terms, a = {}, 0
    m = covered.float()
    denom = m.sum().clamp(min=1.0)
    total = 0.0
    for (name, c), w in zip(TARGETS.items(), weights):
        e = ((pred[:, a:a + c] - target[:, a:a + c]) ** 2).mean(1, keepdim=True)
        terms[name] = (e * m).sum() / denom
        total = total + w * terms[name]
        a += c
    return total, terms


class DecompStage(OptimizerStage, Stage):
    """Batches of (completed albedo, condition) → the four target maps; mirrored half of the time."""

    unit = "step"

    def __init__(self, d: FaceSet, albedo_in: np.ndarray, backbone: ConditionalDiffusion, backbone_id: str,
                 s: DecompSettings, res: int):
        d = at_resolution(d, res)
        self.s, self.name = s, f"train face decomposition ({s.variant})"
        self.digest, self.backbone_id = data_digest(d), backbone_id
        self.cond = condition(d)
        self.alb = np.ascontiguousarray(encode_albedo(albedo_in).transpose(0, 3, 1, 2))
        self.maps = encode_maps({**d.targets, "albedo": normalise_albedo(d.targets["albedo"], d.seen)})
        self.covered = d.mask
        self.geometry = {k: d.geometry[k] for k in ("position", "normal_geo", "tangent")}
        self.eyes = [tuple(map(float, r.get("eye", (0.0, 0.0, 10.0)))) for r in d.records]
        self.fronts = [np.asarray(r["frame"])[2] if "frame" in r else np.array([0.0, 0.0, 1.0]) for r in d.records]
        self.rng = np.random.default_rng(s.seed)
        torch.manual_seed(s.seed)
        self.model = Decomposer(backbone, s)
        lr = s.lr / 5 if s.variant == "independent" else s.lr
        heads = list(self.model.heads.parameters())
        ids = {id(p) for p in heads}
        # the heads start at zero and carry each map's own structure: they learn at 3 × the adapters' rate
        self.opt = torch.optim.AdamW([{"params": [p for p in self.model.trainable() if id(p) not in ids], "lr": lr},
                                      {"params": heads, "lr": 3 * s.lr}], weight_decay=0.0)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": self.digest, "backbone": self.backbone_id}

    def step(self, it: int):
        idx = self.rng.integers(0, len(self.cond), self.s.batch)
        flip = self.rng.random(self.s.batch) < 0.5
        cond, maps, alb = self.cond[idx], self.maps[idx], self.alb[idx]
        cov = self.covered[idx][:, None]
        if flip.any():
            both = np.concatenate([maps[flip], alb[flip]], 1)
            cond[flip], mm = mirror(cond[flip], both)
            maps[flip], alb[flip] = mm[:, :MAP_CHANNELS], mm[:, MAP_CHANNELS:]
            cov[flip] = cov[flip][..., ::-1]
        pred = self.model(torch.from_numpy(alb), torch.from_numpy(cond))
        target, covered = torch.from_numpy(maps), torch.from_numpy(cov.copy())
        loss, terms = decomposition_loss(pred, target, covered, self.s.weights)
        if self.s.shading_weight > 0:
            terms["shading"] = self.shading(idx, flip, pred, target, covered)
            loss = loss + self.s.shading_weight * terms["shading"]
        res = self.backward(loss)
        res.log = {k: float(v.detach()) for k, v in terms.items()}
        return res

    def shading(self, idx, flip, pred, target, covered) -> torch.Tensor:
        """The shading term: two lights within 60° of the face's front (seeded by the stage's rng) + ambient."""
        from mi_plugins.uv_shader import UVLight

        lights, amb = [], []
        for i in idx:
            ls = []
            for _ in range(2):
                d = self.fronts[i] + self.rng.normal(scale=0.6, size=3)
                ls.append(UVLight("directional", tuple(map(float, d / np.linalg.norm(d))), (2.0, 2.0, 2.0)))
            lights.append(ls)
            amb.append(float(self.rng.uniform(0.15, 0.3)))
        geo = {k: v[idx].copy() for k, v in self.geometry.items()}
        for k in geo:  # the maps were mirrored: mirror the texels' geometry with them (same surface points)
            geo[k][flip] = geo[k][flip][:, :, ::-1]
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
        err = uv_shading_error(lights, [self.eyes[i] for i in idx], amb)
        return err(torch_maps(pred), torch_maps(target), t(geo["position"]), t(geo["normal_geo"]), t(geo["tangent"]),
                   covered.permute(0, 2, 3, 1).float().contiguous())

    def finish(self, run: RunState) -> FaceModelResult:
        return FaceModelResult(f"decomposition/{self.s.variant}", self.s, len(self.cond),
                               sum(p.numel() for p in self.model.trainable()), run.summary())


def backbone_id(run: str | Path) -> str:
    from foundation.files import file_digest

    return file_digest(Path(run) / "checkpoint.npz")


def train_decomposer(d: FaceSet, albedo_in: np.ndarray, completion_run: str | Path, out: str | Path,
                     s: DecompSettings | None = None, budget_steps: int | None = None,
                     show_progress: bool = True) -> FaceModelResult | None:
    """Train one decomposition variant on ``d`` with ``albedo_in`` (the completion model's albedo of each instance,
    at the model resolution) on the frozen backbone of ``completion_run``; rerun to resume."""
    s = s or DecompSettings()
    backbone, cs = load_completion(completion_run)
    if albedo_in.shape != (len(d), cs.res, cs.res, 3):
        raise UsageError(f"albedo_in must be ({len(d)}, {cs.res}, {cs.res}, 3), got {albedo_in.shape}")
    bid = backbone_id(completion_run)
    _, result = train_stage(lambda: DecompStage(d, albedo_in, backbone, bid, s, cs.res), out, s, budget_steps, show_progress)
    return result


def load_decomposer(run: str | Path, completion_run: str | Path) -> Decomposer:
    """A trained decomposition variant on its backbone; a checkpoint of another backbone is refused."""
    from foundation.loop import read_checkpoint
    from foundation.records import from_json

    ckpt = Path(run) / "checkpoint.npz"
    if not ckpt.is_file():
        raise UsageError(f"{ckpt}: no face decomposition checkpoint (train one with `photoreal face train-models`)")
    saved = read_checkpoint(ckpt)
    if saved.kind != "DecompStage":
        raise ForeignCheckpointError(f"{ckpt}: a {saved.kind} checkpoint, not a face decomposition's")
    if saved.fingerprint.get("backbone") != backbone_id(completion_run):
        raise CheckpointError(f"{ckpt}: trained on another completion backbone than {completion_run}")
    s = from_json(DecompSettings, saved.fingerprint["settings"], str(ckpt))
    backbone, _ = load_completion(completion_run)
    model = Decomposer(backbone, s)
    try:
        model.load_state_dict(saved.stage["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{ckpt}: weights do not fit the architecture its settings describe "
                              f"({str(exc).splitlines()[0]})") from None
    return model.eval()


@torch.no_grad()
def decompose_maps(model: Decomposer, d: FaceSet, albedo_in: np.ndarray, res: int, batch: int = 4) -> dict[str, np.ndarray]:
    """The four maps (N, res, res, C) of every instance, decoded."""
    d = at_resolution(d, res)
    cond = condition(d)
    alb = np.ascontiguousarray(encode_albedo(albedo_in).transpose(0, 3, 1, 2))
    out = [model(torch.from_numpy(alb[a:a + batch]), torch.from_numpy(cond[a:a + batch])).numpy()
           for a in range(0, len(d), batch)]
    return decode_maps(np.concatenate(out))


