from harness import *
import sys, types; sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from lerobot.policies.pi0_fast import modeling_pi0_fast
from lerobot.policies.pi0_fast.configuration_pi0_fast import PI0FastConfig
import tinypi; tinypi.patch(modeling_pi0_fast, PI0FastConfig, "PI0FastPytorch", force_image_size=32)
from lerobot_armory.demo.standin_tokenizer import build_standin_tokenizer
from lerobot.policies.factory import make_pre_post_processors
import transformers
inp, out = feats(4, 4, ("front",), 64)
cfg = PI0FastConfig(paligemma_variant="tiny", image_resolution=(32, 32), tokenizer_max_length=32, chunk_size=10, n_action_steps=10,
    max_decoding_steps=16, max_action_tokens=16, validate_action_token_prefix=False,
    dtype="float32", input_features=inp, output_features=out, device="cpu")
try:
    modeling_pi0_fast.PI0FastPolicy(cfg)
except Exception as e:
    print("BUILD FAIL (unpatched):", type(e).__name__, e, "| cause:", type(e.__cause__).__name__, str(e.__cause__).splitlines()[0])
# In-process stand-ins for both hub tokenizers (NOT persisted: a saved dir still names the hub ids)
tokdir = build_standin_tokenizer(tempfile.mkdtemp() + "/tok", max_id=tinypi.VOCAB)
standin_text = transformers.AutoTokenizer.from_pretrained(str(tokdir))
tinypi.VOCAB = len(standin_text)  # model vocab == stand-in tokenizer vocab, so every generated id decodes
standin_fast = types.SimpleNamespace(bpe_tokenizer=standin_text, min_token=0, scale=10.0)
class AP:
    @staticmethod
    def from_pretrained(name, **kw): return standin_fast
class AT:
    @staticmethod
    def from_pretrained(name, **kw): return transformers.AutoTokenizer.from_pretrained(str(tokdir), **{k: v for k, v in kw.items() if k != "trust_remote_code"})
modeling_pi0_fast.AutoProcessor = AP; modeling_pi0_fast.AutoTokenizer = AT
import lerobot.processor.tokenizer_processor as tp
tp.AutoProcessor = AP; tp.AutoTokenizer = AT
torch.manual_seed(0)
p = modeling_pi0_fast.PI0FastPolicy(cfg).eval()
pre, post = make_pre_post_processors(cfg, dataset_stats=stats_for(inp, out))
out_, *_ = run(p, pre, post, inp, "pi0_fast", save=False)
print("all zeros (FAST decode fell back)?", bool((out_ == 0).all()))
cfg2 = PI0FastConfig(**{**{f: getattr(cfg, f) for f in ("paligemma_variant","image_resolution","tokenizer_max_length","chunk_size","n_action_steps","max_decoding_steps","max_action_tokens","validate_action_token_prefix","dtype","input_features","output_features","device")}, "temperature": 1.0})
p.config.temperature = 1.0
run(p, pre, post, inp, "pi0_fast_T1", save=False)
