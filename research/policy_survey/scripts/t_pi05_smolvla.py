from harness import *
import sys; sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from lerobot_armory.demo.pi05 import make_pi05_policy
from lerobot_armory.demo.smolvla import make_smolvla_policy
from lerobot_armory.policies import pi05_variants
from lerobot.policies.factory import make_pre_post_processors
for kind in ("pi05", "smolvla"):
    d = tempfile.mkdtemp()
    t = time.time()
    if kind == "pi05":
        make_pi05_policy(d, size="tiny", chunk_size=10, state_dim=4, cameras=("front",), image_size=64)
        from lerobot.policies.pi05.modeling_pi05 import PI05Policy as C
        ov = {"tokenizer_processor": {"tokenizer_name": d + "/tokenizer"}}
        p = C.from_pretrained(d)
    else:
        make_smolvla_policy(d, chunk_size=10, state_dim=4, cameras=("front",), image_size=64)
        from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy as C
        ov = {"tokenizer_processor": {"tokenizer_name": d + "/tokenizer"}}
        p = C.from_pretrained(d)
    pre, post = make_pre_post_processors(p.config, pretrained_path=d, preprocessor_overrides=ov)
    print(f"[{kind}] built+reloaded in {time.time()-t:.1f}s")
    inp = {k: v for k, v in p.config.input_features.items()}
    noise = torch.randn(2, 10, 32)
    run(p, pre, post, inp, kind, kwargs={"noise": noise}, save=False)
    b = batch_for(inp)
    with torch.no_grad():
        a = p.predict_action_chunk(pre(b)); c = p.predict_action_chunk(pre(b)); print(f"[{kind}] no noise arg: repeat identical?", torch.allclose(a, c))
