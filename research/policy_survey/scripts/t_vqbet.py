from harness import *
from lerobot.policies.vqbet.configuration_vqbet import VQBeTConfig
from lerobot.policies.vqbet.modeling_vqbet import VQBeTPolicy
from lerobot.policies.factory import make_pre_post_processors
from lerobot.policies.utils import populate_queues
inp, out = feats(4, 4, ("front",), 64)
cfg = VQBeTConfig(input_features=inp, output_features=out, n_obs_steps=2, n_action_pred_token=3, action_chunk_size=5,
    pretrained_backbone_weights=None, crop_shape=(56, 56), spatial_softmax_num_keypoints=8,
    vqvae_n_embed=8, vqvae_embedding_dim=32, vqvae_enc_hidden_dim=32,
    gpt_block_size=64, gpt_input_dim=64, gpt_output_dim=64, gpt_n_layer=1, gpt_n_head=2, gpt_hidden_dim=64, device="cpu")
torch.manual_seed(0)
p = VQBeTPolicy(cfg).eval()
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
b = batch_for(inp, 2)
with torch.no_grad():
    try:
        print("direct predict_action_chunk:", tuple(p.predict_action_chunk(pre(b)).shape))
    except Exception as e: print("direct predict_action_chunk FAILS:", type(e).__name__, str(e)[:200])
    # workaround: fill the queues the way select_action does, then call predict_action_chunk
    def fill(policy, proc):
        proc = {k: v for k, v in proc.items() if k != "action"}; proc["observation.images"] = torch.stack([proc[k] for k in policy.config.image_features], dim=-4)
        policy._queues = populate_queues(policy._queues, proc)
        return proc
    p.reset(); pb = fill(p, pre(b)); t=time.time(); a = p.predict_action_chunk(pb); dt=time.time()-t
    c = p.predict_action_chunk(pb)
    print("after filling queues:", tuple(a.shape), f"{dt:.2f}s", "repeat identical:", torch.allclose(a, c), "post", tuple(post(a).shape))
d = tempfile.mkdtemp(); p.save_pretrained(d); pre.save_pretrained(d); post.save_pretrained(d)
p2 = VQBeTPolicy.from_pretrained(d); pre2, post2 = make_pre_post_processors(p2.config, pretrained_path=d); print("reload ok", sorted(os.listdir(d)))
