"""2048^2 K=16 scalable mode, peak RSS probe: the 2048^2 inputs and output map, tile 0 (512^2) encoded and its first
sample set decoded (every tile and set has the same size, so this is the peak of the full run). Usage:
  python benchmarks/probe_2048_rss.py small|paper
The full run: python benchmarks/bench_speed.py --large PRESET [--tiles N]."""
import sys, time, resource, torch, numpy as np
from pathlib import Path
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT)); sys.path.insert(0, str(ROOT / 'benchmarks'))
from bench_networks import make_object
from networks.checkpoint import reference_weights
from networks.config import get_config
from networks.model import build_model
from networks.inference import split_sample_sets
torch.set_num_threads(1)
preset = sys.argv[1]
cfg = get_config(preset, "normal"); model = build_model(cfg, reference_weights(cfg, "bench")).eval()
images, mask = make_object(2048, 16)
x, m = torch.from_numpy(images), torch.from_numpy(mask)
out = np.zeros((2048, 2048, 3), np.float32)   # the full-size output map predict_scalable fills
sub = x[:, :, 0::4, 0::4].contiguous(); sm = m[0::4, 0::4].contiguous()
ids = torch.nonzero(sm.reshape(-1)).squeeze(1)
sizes = split_sample_sets(ids.numel(), cfg.pixel_samples)
t = time.process_time()
with torch.inference_mode():
    feats = model.encode(sub[None], sm[None, None].float())
    te = time.process_time() - t
    res = model.decode(sub[None], sm[None, None].float(), feats, ids[None, :sizes[0]])
td = time.process_time() - t - te
print(f"{preset}: tile pixels {ids.numel()} in {len(sizes)} sets; encoder {te:.1f} cpu-s, one set {td:.1f} cpu-s; "
      f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss/1024**2:.2f} GB")
