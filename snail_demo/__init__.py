"""Demonstrations on rendered camera images: printed AprilTags seen by a synthetic camera
(real tag bitmaps, blur, noise, lens distortion), and Turbo the snail robot."""
