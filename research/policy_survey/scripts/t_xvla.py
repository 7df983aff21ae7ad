from harness import *
import sys; sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from lerobot.policies.xvla.configuration_xvla import XVLAConfig
from lerobot.policies.xvla.modeling_xvla import XVLAPolicy
from lerobot.policies.xvla import processor_xvla
from lerobot.policies.factory import make_pre_post_processors
from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer
tok = build_standin_tokenizer(tempfile.mkdtemp() + "/tokenizer", max_id=1024)   # stand-in for facebook/bart-large
inp, out = feats(8, 8, ("front",), 64)
florence = {
    "vision_config": dict(depths=[1, 1], patch_size=[7, 3], patch_stride=[4, 2], patch_padding=[3, 1], patch_prenorm=[False, True],
                          embed_dim=[16, 32], num_heads=[2, 2], num_groups=[2, 2], window_size=4, projection_dim=64,
                          max_position_embeddings=16, max_temporal_embeddings=4),
    "text_config": dict(model_type="bart", vocab_size=1024, d_model=64, encoder_layers=1, decoder_layers=1,
                        encoder_attention_heads=2, decoder_attention_heads=2, encoder_ffn_dim=128, decoder_ffn_dim=128,
                        max_position_embeddings=256),
}
cfg = XVLAConfig(input_features=inp, output_features=out, florence_config=florence, tokenizer_name=str(tok),
    tokenizer_max_length=16, hidden_size=64, depth=1, num_heads=2, len_soft_prompts=4, num_denoising_steps=3,
    chunk_size=10, n_action_steps=10, action_mode="auto", max_action_dim=8, max_state_dim=8, resize_imgs_with_padding=(64, 64), device="cpu")
torch.manual_seed(0)
t = time.time(); p = XVLAPolicy(cfg).eval(); print(f"built in {time.time()-t:.1f}s")
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
o, p2, pre2, post2, d = run(p, pre, post, inp, "xvla")
