"""Held-out evaluation: rendering and scoring, PSNR/SSIM/LPIPS, summaries."""
