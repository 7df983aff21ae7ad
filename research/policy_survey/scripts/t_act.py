from harness import *
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from lerobot.policies.factory import make_pre_post_processors
inp, out = feats(4, 4, ("front",), 64)
cfg = ACTConfig(input_features=inp, output_features=out, chunk_size=10, n_action_steps=10,
    pretrained_backbone_weights=None, dim_model=64, dim_feedforward=128, n_heads=2,
    n_encoder_layers=1, n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=8, device="cpu")
torch.manual_seed(0)
p = ACTPolicy(cfg)
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
o, p2, pre2, post2, d = run(p, pre, post, inp, "act")
b = batch_for(inp); 
with torch.no_grad():
    print("reloaded equal:", torch.allclose(p.predict_action_chunk(pre(b)), p2.predict_action_chunk(pre2(b))))
