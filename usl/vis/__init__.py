"""Drawing primitives shared by evaluation pictures, predictions and previews: PNG output, boxes, overlays, palette."""
