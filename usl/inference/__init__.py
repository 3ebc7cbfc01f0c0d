"""Running a trained model on images: detections, 3D objects and their glTF / OBJ / PLY / HTML scene export."""
