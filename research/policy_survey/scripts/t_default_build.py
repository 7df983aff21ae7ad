"""Build <type> with its default config (tiny features) and report the first failure."""
import sys, time
from harness import *
from lerobot.policies.factory import get_policy_class, make_policy_config
t = sys.argv[1]
inp, out = feats(4, 4, ("front",), 224)
try:
    cfg = make_policy_config(t, input_features=inp, output_features=out, device="cpu")
except Exception as e:
    print(f"[{t}] CONFIG FAIL: {type(e).__name__}: {str(e).splitlines()[0][:300]}"); sys.exit()
t0 = time.time()
try:
    p = get_policy_class(t)(cfg)
    print(f"[{t}] BUILT?! params={sum(x.numel() for x in p.parameters())/1e6:.1f}M in {time.time()-t0:.1f}s")
except BaseException as e:
    c = e.__cause__ or e.__context__
    print(f"[{t}] BUILD FAIL after {time.time()-t0:.1f}s: {type(e).__name__}: {str(e).splitlines()[0][:300] if str(e) else ''}" + (f" | cause {type(c).__name__}: {str(c).splitlines()[0][:200]}" if c else ""))
