"""Training helpers beyond the rendering pass: cached G-buffers for texture-only marks (`gbuffer`)."""
