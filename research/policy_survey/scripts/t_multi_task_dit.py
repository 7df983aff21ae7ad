from harness import *
import sys; sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from transformers import CLIPConfig, CLIPModel
from lerobot.policies.multi_task_dit.configuration_multi_task_dit import MultiTaskDiTConfig
from lerobot.policies.multi_task_dit.modeling_multi_task_dit import MultiTaskDiTPolicy
from lerobot.policies.factory import make_pre_post_processors
from lerobot.policies.utils import populate_queues
from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer
# stand-in for openai/clip-vit-base-patch16: tiny random CLIP + stand-in tokenizer in one local dir
clip_dir = tempfile.mkdtemp() + "/clip"
cc = CLIPConfig(text_config=dict(vocab_size=1024, hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, max_position_embeddings=32),
                vision_config=dict(hidden_size=32, intermediate_size=64, num_hidden_layers=1, num_attention_heads=2, image_size=32, patch_size=8), projection_dim=32)
CLIPModel(cc).save_pretrained(clip_dir)
build_standin_tokenizer(clip_dir, max_id=1024)
inp, out = feats(4, 4, ("front",), 64)
cfg = MultiTaskDiTConfig(input_features=inp, output_features=out, n_obs_steps=2, horizon=16, n_action_steps=8,
    vision_encoder_name=clip_dir, text_encoder_name=clip_dir, image_crop_shape=(32, 32), image_resize_shape=(32, 32), tokenizer_max_length=16,
    hidden_dim=64, num_layers=1, num_heads=2, timestep_embed_dim=32, num_inference_steps=4, noise_scheduler_type="DDIM", device="cpu")
torch.manual_seed(0)
t = time.time(); p = MultiTaskDiTPolicy(cfg).eval(); print(f"built in {time.time()-t:.1f}s")
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
b = batch_for(inp)
with torch.no_grad():
    try: print("direct predict_action_chunk:", tuple(p.predict_action_chunk(pre(b)).shape))
    except Exception as e: print("direct predict_action_chunk FAILS:", type(e).__name__, str(e)[:200])
    pb = p._prepare_batch({k: v for k, v in pre(b).items() if k != "action"})
    p.reset(); p._queues = populate_queues(p._queues, pb)
    t = time.time(); a = p.predict_action_chunk(dict(pb)); dt = time.time() - t; c = p.predict_action_chunk(dict(pb))
    print("after filling queues:", tuple(a.shape), f"{dt:.2f}s", "repeat identical:", torch.allclose(a, c), "post", tuple(post(a).shape))
d = tempfile.mkdtemp(); p.save_pretrained(d); pre.save_pretrained(d); post.save_pretrained(d)
p2 = MultiTaskDiTPolicy.from_pretrained(d); pre2, post2 = make_pre_post_processors(p2.config, pretrained_path=d); print("reload ok", sorted(os.listdir(d)))
