//! Image preprocessing for descriptor networks: grayscale u8 -> the float tensor the model
//! expects (the same steps as `model/build_model.py`, which fits the model on them).

/// ImageNet channel means and standard deviations (RGB), the normalization every
/// ImageNet-pretrained backbone (and NetVLAD / CosPlace exports) is trained with.
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// An 8-bit grayscale image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct GrayImage {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<u8>,
}

impl GrayImage {
    /// `None` when the pixel count disagrees with the size or the size is zero.
    pub fn new(width: usize, height: usize, pixels: Vec<u8>) -> Option<Self> {
        (width > 0 && height > 0 && pixels.len() == width * height).then_some(Self {
            width,
            height,
            pixels,
        })
    }
}

/// Weights of area resampling from `n_in` to `n_out` samples: output `j` averages the
/// input interval `[j s, (j + 1) s)`, `s = n_in / n_out`, each input sample weighted by
/// its overlap with it. Unlike bilinear sampling, it does not alias when shrinking
/// (752 -> 320 is a factor 2.35). Returns `(first input index, weights)` per output.
fn area_weights(n_in: usize, n_out: usize) -> Vec<(usize, Vec<f32>)> {
    let s = n_in as f64 / n_out as f64;
    (0..n_out)
        .map(|j| {
            let (lo, hi) = (j as f64 * s, (j + 1) as f64 * s);
            let first = lo.floor() as usize;
            let last = (hi.ceil() as usize).min(n_in);
            let w = (first..last)
                .map(|i| ((hi.min(i as f64 + 1.0) - lo.max(i as f64)) / s) as f32)
                .collect();
            (first, w)
        })
        .collect()
}

/// Resizes `img` to `width x height` by area resampling; values in [0, 1].
pub fn resize_area(img: &GrayImage, width: usize, height: usize) -> Vec<f32> {
    let rows = area_weights(img.height, height);
    let cols = area_weights(img.width, width);
    let mut out = Vec::with_capacity(width * height);
    let mut acc = vec![0f32; img.width];
    for (first, weights) in &rows {
        acc.iter_mut().for_each(|a| *a = 0.0);
        for (k, &w) in weights.iter().enumerate() {
            let row = &img.pixels[(first + k) * img.width..][..img.width];
            for (a, &p) in acc.iter_mut().zip(row) {
                *a += w * f32::from(p);
            }
        }
        out.extend(cols.iter().map(|(first, weights)| {
            weights
                .iter()
                .zip(&acc[*first..])
                .map(|(w, a)| w * a)
                .sum::<f32>()
                / 255.0
        }));
    }
    out
}

/// The model input of one image, `[channels, height, width]` row-major: area resize,
/// ImageNet normalization, the gray value replicated to 3 channels (or one channel
/// normalized with the mean of the three statistics, for 1-channel models).
pub fn to_tensor(img: &GrayImage, channels: usize, width: usize, height: usize) -> Vec<f32> {
    let plane = resize_area(img, width, height);
    let stats: Vec<(f32, f32)> = if channels == 3 {
        (0..3)
            .map(|c| (IMAGENET_MEAN[c], IMAGENET_STD[c]))
            .collect()
    } else {
        let mean = IMAGENET_MEAN.iter().sum::<f32>() / 3.0;
        let std = IMAGENET_STD.iter().sum::<f32>() / 3.0;
        vec![(mean, std); channels]
    };
    stats
        .iter()
        .flat_map(|&(m, s)| plane.iter().map(move |v| (v - m) / s))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn area_resize_averages_blocks() {
        // 4x2 -> 2x1: each output is the mean of a 2x2 block.
        let img = GrayImage::new(4, 2, vec![0, 255, 51, 51, 255, 0, 51, 51]).unwrap();
        let out = resize_area(&img, 2, 1);
        assert!(
            (out[0] - 0.5).abs() < 1e-6 && (out[1] - 0.2).abs() < 1e-6,
            "{out:?}"
        );
        // Non-integer factor: a constant image stays constant.
        let flat = GrayImage::new(752, 480, vec![100; 752 * 480]).unwrap();
        let out = resize_area(&flat, 320, 208);
        assert_eq!(out.len(), 320 * 208);
        assert!(out.iter().all(|v| (v - 100.0 / 255.0).abs() < 1e-5));
    }

    #[test]
    fn tensor_is_imagenet_normalized_and_replicated() {
        let img = GrayImage::new(2, 2, vec![255; 4]).unwrap();
        let t = to_tensor(&img, 3, 1, 1);
        for c in 0..3 {
            let want = (1.0 - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
            assert!((t[c] - want).abs() < 1e-5, "{t:?}");
        }
        assert!(GrayImage::new(2, 2, vec![0; 3]).is_none());
    }
}
