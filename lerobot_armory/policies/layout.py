"""What lerobot-armory reads from a policy directory besides LeRobot's own files.

The engine reads these when it loads ``--policy.path``; the offline builders
(:mod:`lerobot_armory.demo`) write them. They live here, below both.
"""

# Optional sidecar a policy directory may carry (the demo policy writes it): action names.
SIDECAR = "armory.json"
# A tokenizer stored inside the policy directory (the π0.5 demo's stand-in) replaces the one the
# saved pre-processor names, wherever the directory has been moved to.
TOKENIZER_DIR = "tokenizer"
VLM_DIR = "vlm"  # a stand-in VLM inside the directory (the SmolVLA demo's)
# A stand-in CLIP inside the directory (the Multi-Task DiT demo's image and text encoders); the
# name must contain "clip" (LeRobot checks it).
CLIP_DIR = "clip"
# A stand-in FAST action tokenizer inside the directory (the π0-FAST demo's).
FAST_DIR = "fast"
