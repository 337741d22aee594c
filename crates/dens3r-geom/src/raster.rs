//! A row-major 2-D grid of values (depth maps, pointmaps, normal maps, labels).

use thiserror::Error;

/// Error for a buffer whose length does not match its stated size.
#[derive(Debug, Error)]
#[error("raster of {width}x{height} needs {expected} values, got {got}")]
pub struct RasterError {
    /// Stated width.
    pub width: usize,
    /// Stated height.
    pub height: usize,
    /// `width * height`.
    pub expected: usize,
    /// Length of the buffer handed in.
    pub got: usize,
}

/// Row-major `height x width` grid; `data[y * width + x]` is pixel `(x, y)`.
#[derive(Debug, Clone, PartialEq)]
pub struct Raster<T> {
    width: usize,
    height: usize,
    data: Vec<T>,
}

impl<T: Clone> Raster<T> {
    /// A raster filled with `value`.
    pub fn filled(width: usize, height: usize, value: T) -> Self {
        Self { width, height, data: vec![value; width * height] }
    }
}

impl<T> Raster<T> {
    /// Wraps a row-major buffer; fails if its length is not `width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<T>) -> Result<Self, RasterError> {
        let expected = width * height;
        if data.len() != expected {
            return Err(RasterError { width, height, expected, got: data.len() });
        }
        Ok(Self { width, height, data })
    }

    /// Builds a raster by calling `f(x, y)` for every pixel.
    pub fn from_fn(width: usize, height: usize, mut f: impl FnMut(usize, usize) -> T) -> Self {
        let mut data = Vec::with_capacity(width * height);
        for y in 0..height {
            for x in 0..width {
                data.push(f(x, y));
            }
        }
        Self { width, height, data }
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The row-major values.
    pub fn data(&self) -> &[T] {
        &self.data
    }

    /// Mutable row-major values.
    pub fn data_mut(&mut self) -> &mut [T] {
        &mut self.data
    }

    /// Consumes the raster and returns its buffer.
    pub fn into_vec(self) -> Vec<T> {
        self.data
    }

    /// Value at column `x`, row `y` (panics when out of range, like slice indexing).
    #[inline]
    pub fn get(&self, x: usize, y: usize) -> &T {
        &self.data[y * self.width + x]
    }

    /// Mutable value at column `x`, row `y`.
    #[inline]
    pub fn get_mut(&mut self, x: usize, y: usize) -> &mut T {
        &mut self.data[y * self.width + x]
    }

    /// A new raster with `f` applied to every value.
    pub fn map<U>(&self, f: impl FnMut(&T) -> U) -> Raster<U> {
        Raster { width: self.width, height: self.height, data: self.data.iter().map(f).collect() }
    }

    /// True when both rasters have the same width and height.
    pub fn same_size<U>(&self, other: &Raster<U>) -> bool {
        self.width == other.width && self.height == other.height
    }
}
