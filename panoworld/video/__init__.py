"""The video stage: condition frames filled into a panoramic video (background layer, inpainting, generators)."""
