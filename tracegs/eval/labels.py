"""How methods and metrics are named and rounded in every table of the report."""

from tracegs.products import Product

METHOD_LABELS = {"3dgs": "3DGS", "baseline": "Baseline (A)", "tracegs": "TRACE-GS"}
# Restorers that appear only in diagnostics (the privileged gap), never as evaluation methods.
# The Stage-1 adapter's name as a restorer of its own (the diagnostics' row and teacher, the privileged report's row).
STAGE1 = Product.stage1.value
RESTORER_LABELS = {**METHOD_LABELS, STAGE1: "Stage-1 adapter", "tracegs": "Stage-2 student (TRACE-GS)"}
# SSIM′ is the second SSIM column, the convention the headline SSIM does not use (tracegs.eval.metrics).
METRIC_LABELS = {"psnr": "PSNR↑", "ssim": "SSIM↑", "lpips": "LPIPS↓", "ssim_alt": "SSIM′↑"}
METRIC_DECIMALS = {"psnr": 2, "ssim": 3, "lpips": 3, "ssim_alt": 3}
HIGHER_IS_BETTER = {"psnr": True, "ssim": True, "lpips": False, "ssim_alt": True}
# Table 3's column groups (paper: DL3DV-Benchmark in domain, Mip-NeRF 360 out of domain), by data option.
DATASET_LABELS = {"dl3dv": "DL3DV", "mipnerf360": "Mip-NeRF 360", "nerfbusters": "NeRFBusters",
                  "synthetic": "Synthetic"}
