"""Tiny-variant patch for LeRobot's pi0 / pi0_fast modules (same idea as lerobot_armory.policies.pi05_variants)."""
import contextlib
TINY = dict(width=64, depth=2, mlp_dim=128, num_heads=2, num_kv_heads=1, head_dim=32)
VOCAB = 1024
VIS = dict(hidden_size=32, num_hidden_layers=1, num_attention_heads=2, intermediate_size=64, patch_size=8)

def patch(m, cfg_cls, pytorch_cls_name, force_image_size=None):
    real_get = m.get_gemma_config
    real_vlm = m.PaliGemmaForConditionalGenerationWithPiGemma
    real_exp = getattr(m, "PiGemmaForCausalLM", None)
    real_post = cfg_cls.__post_init__
    def post(self):
        names = {f: getattr(self, f) for f in ("paligemma_variant", "action_expert_variant") if getattr(self, f, None) == "tiny"}
        for f in names: setattr(self, f, "gemma_300m")
        try: real_post(self)
        finally:
            for f, n in names.items(): setattr(self, f, n)
    cfg_cls.__post_init__ = post
    m.get_gemma_config = lambda v: m.GemmaConfig(**TINY) if v == "tiny" else real_get(v)
    def vlm(config):
        vc = config.vision_config
        for k, v in VIS.items(): setattr(vc, k, v)
        vc.projection_dim = config.text_config.hidden_size
        if force_image_size: vc.image_size = force_image_size  # pi0_fast leaves SigLIP at its 224 default
        config.text_config.vocab_size = VOCAB
        return real_vlm(config=config)
    m.PaliGemmaForConditionalGenerationWithPiGemma = vlm
    if real_exp is not None:
        def exp(config):
            config.vocab_size = VOCAB
            return real_exp(config=config)
        m.PiGemmaForCausalLM = exp
