"""Visualization: headless renders, PCK figures, TensorBoard meshes."""
