from harness import *
import sys; sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from lerobot.policies.pi0 import modeling_pi0, processor_pi0
from lerobot.policies.pi0.configuration_pi0 import PI0Config
import tinypi; tinypi.patch(modeling_pi0, PI0Config, "PI0Pytorch")
from lerobot.policies.pi0.modeling_pi0 import PI0Policy
from lerobot.policies.factory import make_pre_post_processors
from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer
tok = build_standin_tokenizer(tempfile.mkdtemp() + "/tokenizer", max_id=tinypi.VOCAB)
inp, out = feats(4, 4, ("front",), 64)
cfg = PI0Config(paligemma_variant="tiny", action_expert_variant="tiny", image_resolution=(32, 32), tokenizer_max_length=32,
    chunk_size=10, n_action_steps=10, num_inference_steps=3, dtype="float32", input_features=inp, output_features=out, device="cpu")
torch.manual_seed(0)
t = time.time(); p = PI0Policy(cfg).eval(); print(f"built in {time.time()-t:.1f}s")
real = processor_pi0.TokenizerProcessorStep
processor_pi0.TokenizerProcessorStep = lambda **kw: real(**{**kw, "tokenizer_name": str(tok)})
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
processor_pi0.TokenizerProcessorStep = real
noise = torch.randn(2, 10, 32)
o, p2, pre2, post2, d = run(p, pre, post, inp, "pi0", kwargs={"noise": noise})
b = batch_for(inp)
with torch.no_grad():
    a = p.predict_action_chunk(pre(b)); c = p.predict_action_chunk(pre(b)); print("no noise arg: repeat identical?", torch.allclose(a, c))
    print("reloaded equal (same noise):", torch.allclose(p.predict_action_chunk(pre(b), noise=noise), p2.predict_action_chunk(pre2(b), noise=noise)))
