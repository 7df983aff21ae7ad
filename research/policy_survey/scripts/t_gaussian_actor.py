from harness import *
from lerobot.policies.gaussian_actor.configuration_gaussian_actor import GaussianActorConfig, ActorNetworkConfig
from lerobot.policies.gaussian_actor.modeling_gaussian_actor import GaussianActorPolicy
from lerobot.policies.factory import make_pre_post_processors
inp, out = feats(4, 4, ("front",), 64)
cfg = GaussianActorConfig(input_features=inp, output_features=out, latent_dim=16, state_encoder_hidden_dim=16,
    image_encoder_hidden_dim=8, actor_network_kwargs=ActorNetworkConfig(hidden_dims=[32, 32]), device="cpu")
torch.manual_seed(0)
p = GaussianActorPolicy(cfg).eval()
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
b = batch_for(inp, 2)
with torch.no_grad():
    try: print("predict_action_chunk:", tuple(p.predict_action_chunk(pre(b)).shape))
    except Exception as e: print("predict_action_chunk FAILS:", type(e).__name__, str(e)[:200])
    pb = pre(b); t = time.time(); a = p.select_action(pb); dt = time.time() - t; c = p.select_action(pb)
    print("select_action:", tuple(a.shape), f"{dt:.3f}s", "repeat identical:", torch.allclose(a, c), "post", tuple(post(a).shape))
d = tempfile.mkdtemp(); p.save_pretrained(d); pre.save_pretrained(d); post.save_pretrained(d)
p2 = GaussianActorPolicy.from_pretrained(d); pre2, post2 = make_pre_post_processors(p2.config, pretrained_path=d); print("reload ok", sorted(os.listdir(d)))
