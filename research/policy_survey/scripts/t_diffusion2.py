from harness import *
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_pre_post_processors
inp, out = feats(4, 4, ("front",), 64)
for nobs, sched in ((1, "DDPM"), (2, "DDIM")):
    cfg = DiffusionConfig(input_features=inp, output_features=out, n_obs_steps=nobs, horizon=16, n_action_steps=8,
        pretrained_backbone_weights=None, crop_shape=(56, 56), down_dims=(32, 64), diffusion_step_embed_dim=32,
        spatial_softmax_num_keypoints=8, num_inference_steps=4, noise_scheduler_type=sched, device="cpu")
    p = DiffusionPolicy(cfg).eval()
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
    b = batch_for(inp, 2)
    if nobs == 2:
        b["observation.state"] = torch.randn(2, 2, 4); b["observation.images.front"] = torch.rand(2, 2, 3, 64, 64)
    noise = torch.randn(2, 16, 4)
    with torch.no_grad():
        try:
            a = p.predict_action_chunk(pre(b), noise=noise); c = p.predict_action_chunk(pre(b), noise=noise)
            print(nobs, sched, "shape", tuple(a.shape), "same noise -> identical:", torch.allclose(a, c))
        except Exception as e:
            import traceback; traceback.print_exc()
