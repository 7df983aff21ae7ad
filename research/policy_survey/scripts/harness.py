"""Shared helper: build features/stats, run pre -> predict_action_chunk -> post on a random batch of 2, save+reload."""
import os, sys, time, tempfile, shutil, traceback
os.environ.setdefault("HF_HUB_OFFLINE", "1"); os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
import torch
torch.set_num_threads(1)
from lerobot.configs.types import FeatureType, PolicyFeature, NormalizationMode

def feats(state_dim=4, action_dim=4, cams=("front",), img=64, image_key_fmt="observation.images.{}", env_state=None):
    inp = {"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,))}
    for c in cams:
        inp[image_key_fmt.format(c)] = PolicyFeature(FeatureType.VISUAL, (3, img, img))
    if env_state:
        inp["observation.environment_state"] = PolicyFeature(FeatureType.ENV, (env_state,))
    return inp, {"action": PolicyFeature(FeatureType.ACTION, (action_dim,))}

def stats_for(inp, out):
    s = {}
    for k, f in {**inp, **out}.items():
        if f.type == FeatureType.VISUAL:
            s[k] = {"mean": torch.full((3, 1, 1), 0.5), "std": torch.full((3, 1, 1), 0.25), "min": torch.zeros(3,1,1), "max": torch.ones(3,1,1)}
        else:
            d = f.shape[0]; o = torch.ones(d)
            s[k] = {"mean": 0 * o, "std": o, "min": -o, "max": o, "q01": -o, "q99": o, "q10": -o, "q90": o}
    return s

def batch_for(inp, B=2, task="pick up the cube", img=None):
    b = {}
    for k, f in inp.items():
        if f.type == FeatureType.VISUAL:
            b[k] = torch.rand(B, *f.shape)
        else:
            b[k] = torch.randn(B, *f.shape)
    b["task"] = [task] * B
    return b

def run(policy, pre, post, inp, label, B=2, kwargs=None, save=True, policy_cls=None, reload_kwargs=None, batch=None):
    kwargs = kwargs or {}
    policy.eval()
    batch = batch if batch is not None else batch_for(inp, B)
    t0 = time.time()
    with torch.no_grad():
        proc = pre(batch)
        t1 = time.time()
        out = policy.predict_action_chunk(proc, **kwargs)
        t2 = time.time()
        act = post(out)
    print(f"[{label}] params={sum(p.numel() for p in policy.parameters())/1e6:.3f}M  model out {tuple(out.shape)}  post {tuple(act.shape)}  pre {t1-t0:.2f}s predict {t2-t1:.2f}s", flush=True)
    with torch.no_grad():
        out2 = policy.predict_action_chunk(pre(batch), **kwargs)
    print(f"[{label}] second call same input identical? {torch.allclose(out, out2)} maxdiff={float((out-out2).abs().max()):.3g}", flush=True)
    if save:
        d = tempfile.mkdtemp(prefix=f"{label}_")
        policy.save_pretrained(d); pre.save_pretrained(d); post.save_pretrained(d)
        cls = policy_cls or type(policy)
        t0 = time.time()
        p2 = cls.from_pretrained(d, **(reload_kwargs or {}))
        p2.eval()
        from lerobot.policies.factory import make_pre_post_processors
        pre2, post2 = make_pre_post_processors(p2.config, pretrained_path=d)
        print(f"[{label}] reload ok in {time.time()-t0:.2f}s; files={sorted(os.listdir(d))}", flush=True)
        return out, p2, pre2, post2, d
    return out, None, None, None, None
