"""DP defocus deblurring (the paper's Sec. 5.3): a DPDNet-like U-Net from the two DP views to the sharp image,
its training and evaluation (``dp5k deblur``), and the downstream study of every simulator (``dp5k study downstream``).

Modules: :mod:`.model` (the network), :mod:`.config` (dataclass configs), :mod:`.train` (training on any format-v1
dataset through :mod:`dp5k_learn`, fine-tuning), :mod:`.evaluate` (masked MAE / PSNR / SSIM against
``sharp`` beside the blurred input), :mod:`.study` (Tables 3 and 4), :mod:`.cli` (the commands).
Imports only ``dp5k_common``, ``dp5k_learn`` (the training tools) and ``neural_dp.registry`` (the simulators and
synthesis).
"""
