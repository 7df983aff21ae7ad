from harness import *
from lerobot.policies.tdmpc.configuration_tdmpc import TDMPCConfig
from lerobot.policies.tdmpc.modeling_tdmpc import TDMPCPolicy
from lerobot.policies.factory import make_pre_post_processors
from lerobot.policies.utils import populate_queues
inp, out = feats(4, 4, ("front",), 64, image_key_fmt="observation.image")  # TD-MPC reads OBS_IMAGE = "observation.image"
cfg = TDMPCConfig(input_features=inp, output_features=out, horizon=5, n_action_steps=5, n_action_repeats=1,
    latent_dim=16, mlp_dim=32, state_encoder_hidden_dim=32, image_encoder_hidden_dim=8, q_ensemble_size=2,
    n_gaussian_samples=16, n_pi_samples=4, n_elites=4, cem_iterations=2, device="cpu")
torch.manual_seed(0)
p = TDMPCPolicy(cfg).eval()
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
b = batch_for(inp, 2)
with torch.no_grad():
    try: print("direct predict_action_chunk:", tuple(p.predict_action_chunk(pre(b)).shape))
    except Exception as e: print("direct predict_action_chunk FAILS:", type(e).__name__, str(e)[:200])
    pb = {k: v for k, v in pre(b).items() if k != "action"}
    p.reset(); p._queues = populate_queues(p._queues, pb)
    t=time.time(); a = p.predict_action_chunk(pb); dt=time.time()-t
    print("after filling queues:", tuple(a.shape), f"{dt:.2f}s  (time-major: horizon, B, D)", "_prev_mean set:", p._prev_mean is not None)
    try:
        pb3 = {k: v for k, v in pre(batch_for(inp, 3)).items() if k != "action"}; p._queues = populate_queues(p._queues, pb3)
        print("next call with B=3:", tuple(p.predict_action_chunk(pb3).shape))
    except Exception as e: print("next call with B=3 (prev_mean from B=2) FAILS:", type(e).__name__, str(e)[:200])
    try: print("post on (H,B,D):", tuple(post(a).shape))
    except Exception as e: print("post FAILS", e)
d = tempfile.mkdtemp(); p.save_pretrained(d); pre.save_pretrained(d); post.save_pretrained(d)
p2 = TDMPCPolicy.from_pretrained(d); pre2, post2 = make_pre_post_processors(p2.config, pretrained_path=d); print("reload ok", sorted(os.listdir(d)))
