"""`aesplat bench`: what accuracy costs in time, for every knob that trades one for the other (docs/bench.md).

    aesplat bench --ckpt CKPT [--out DIR]

For a trained model on evaluation scenes, each knob is swept on its own from a baseline (every SH band, the
data's resolution, all Gaussians, fp32, the default renderer backend):

    sh_degree         SH bands used when rendering (0 .. the model's degree)
    context_views     context views fed to the model (2, 3, 4, 6): each evaluation sample's k-view context
                      (the one `aesplat test --data.num_context_views k` evaluates), the same target views
    input_size        side of the images fed to the model (multiples of its patch size); Gaussians rendered
                      at full size
    render_size       side of the rendered image, upsampled (bilinear) to full size for the metrics
    keep_fraction     only the most opaque fraction of the Gaussians is rendered
    min_opacity       Gaussians below an opacity threshold are dropped
    precision         fp32, or bf16 autocast around the model forward (the renderer is always fp32)
    backend           renderer backends available here (torch, torch compiled, gsplat with CUDA)

Quality is PSNR (per image, then averaged) and SSIM against the ground-truth target images, rendered with
the *predicted* target cameras (the data set's for a checkpoint trained with ``model.cameras: dataset``),
and the rotation error of the predicted cameras against the data set's (degrees, views relative to view 0).
Time is milliseconds per scene for the model forward and for rendering the target views: median over repeats
of each scene (warm-up runs excluded), then averaged over scenes.

Writes DIR/bench.csv, DIR/BENCH.md (tables), DIR/accuracy_vs_time.png (quality against milliseconds, one
series per knob) and DIR/bench.json (rows plus the machine and settings they were measured with).
"""
