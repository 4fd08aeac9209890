"""Regenerate astronaut_landmarks.npy: MediaPipe 0.10.14 face mesh on scikit-image's astronaut.png."""

from pathlib import Path

import numpy as np
import skimage.data

from inverse.face import detect_landmarks

if __name__ == "__main__":
    np.save(Path(__file__).with_name("astronaut_landmarks.npy"), detect_landmarks(skimage.data.astronaut()))
