"""Convert a training run's weights to float16 safetensors, keeping the metadata (config and card)."""
import sys, os
from safetensors import safe_open
from safetensors.torch import load_file, save_file
import torch
src, dst = sys.argv[1], sys.argv[2]
if os.path.exists(src):
    with safe_open(src, "pt") as f:
        meta = f.metadata()
    st = {k: v.to(torch.float16) if v.is_floating_point() else v for k, v in load_file(src).items()}
    save_file(st, dst, metadata=meta)
    print("exported", dst, os.path.getsize(dst))
