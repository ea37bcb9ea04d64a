"""Training: one pass of the pipeline on a batch (`step`), its views (`views`), losses and the
seed's distortions (`losses`, `distortions`), the trainer (`train`), cached G-buffers for texture-only
marks (`gbuffer`), data-parallel runs (`distributed`) and decoder fine-tuning on another engine's
pictures (`finetune`)."""
