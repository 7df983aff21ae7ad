from harness import *
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
from lerobot.policies.factory import make_pre_post_processors
inp, out = feats(4, 4, ("front",), 64)
cfg = DiffusionConfig(input_features=inp, output_features=out, n_obs_steps=2, horizon=16, n_action_steps=8,
    pretrained_backbone_weights=None, crop_shape=(56, 56), down_dims=(32, 64), diffusion_step_embed_dim=32,
    spatial_softmax_num_keypoints=8, num_inference_steps=4, device="cpu")
torch.manual_seed(0)
p = DiffusionPolicy(cfg)
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
# predict_action_chunk with empty queues: "offline" mode uses the batch directly; needs (B, n_obs_steps, ...) history
B = 2
b = batch_for(inp, B)
b["observation.state"] = torch.randn(B, 2, 4); b["observation.images.front"] = torch.rand(B, 2, 3, 64, 64)
noise = torch.randn(B, 16, 4)
o, p2, pre2, post2, d = run(p, pre, post, inp, "diffusion", batch=b, kwargs={"noise": noise})
with torch.no_grad():
    a = p.predict_action_chunk(pre(b)); c = p.predict_action_chunk(pre(b))
    print("without noise arg: two calls equal?", torch.allclose(a, c))
    print("reloaded equal (same noise):", torch.allclose(p.predict_action_chunk(pre(b), noise=noise), p2.predict_action_chunk(pre2(b), noise=noise)))
    # single-step obs (B, D) with n_obs_steps=2:
    try:
        b1 = batch_for(inp, B); p.reset(); print("n_obs_steps=2 with single-step batch ->", tuple(p.predict_action_chunk(pre(b1)).shape))
    except Exception as e: print("single-step batch with n_obs_steps=2 FAILS:", type(e).__name__, str(e)[:200])
    # after select_action, queues populated -> predict_action_chunk ignores batch and uses queue
    p.reset(); b1 = batch_for(inp, B); p.select_action(pre(b1))
    try:
        b3 = batch_for(inp, 3); print("after select_action(B=2), predict_action_chunk(B=3) ->", tuple(p.predict_action_chunk(pre(b3)).shape))
    except Exception as e: print("after select_action(B=2), predict_action_chunk(B=3) FAILS:", type(e).__name__, str(e)[:200])
