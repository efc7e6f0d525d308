#![forbid(unsafe_code)]
//! Frame numbers from scan timestamps: a scan that arrives two sensor periods after the previous one
//! comes after one missing scan, though no file is missing (a dropped frame of the driver or the log).

use std::collections::VecDeque;

use crate::error::{Error, Result};

/// The sensor period is the median of this many intervals between consecutive scans.
pub const RECENT_INTERVALS: usize = 50;

/// Counts frames: one per scan, or as many sensor periods as a scan's timestamp lies after the last
/// timestamped one (the period measured as the median interval between consecutive scans).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FrameClock {
    frame: Option<u64>,
    last: Option<(f64, u64)>,
    intervals: VecDeque<f64>,
}

/// The frame a scan was given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tick {
    /// Its frame number (the first scan's is 0).
    pub frame: u64,
    /// Its timestamp was not after the previous timestamped scan's: it was taken for the next frame.
    pub out_of_order: bool,
    /// The previous timestamped scan's timestamp, if any.
    pub previous: Option<f64>,
}

impl FrameClock {
    /// A clock before the first scan.
    pub fn new() -> Self {
        Self::default()
    }

    /// The newest scan's frame number; `None` before the first.
    pub fn frame(&self) -> Option<u64> {
        self.frame
    }

    /// The sensor period in the timestamps' unit, once two consecutive scans had timestamps.
    pub fn period(&self) -> Option<f64> {
        if self.intervals.is_empty() {
            return None;
        }
        let mut sorted: Vec<f64> = self.intervals.iter().copied().collect();
        sorted.sort_by(f64::total_cmp);
        let middle = sorted.len() / 2;
        Some(if sorted.len() % 2 == 1 {
            sorted[middle]
        } else {
            0.5 * (sorted[middle - 1] + sorted[middle])
        })
    }

    /// The frame of the next scan, `timestamp` its time (any unit, increasing) or `None`. A timestamp
    /// that is not finite is an error and leaves the clock as it was.
    pub fn advance(&mut self, timestamp: Option<f64>) -> Result<Tick> {
        if let Some(time) = timestamp {
            if !time.is_finite() {
                return Err(Error::invalid(
                    "timestamp",
                    format!("expected a finite number (seconds), got {time}"),
                ));
            }
        }
        let mut out_of_order = false;
        let previous = self.last.map(|(time, _)| time);
        let frames = match (timestamp, self.last) {
            (Some(time), Some(last)) => {
                let (frames, backwards) = self.frames_since_last(time, last);
                out_of_order = backwards;
                frames
            }
            _ => 1,
        };
        let frame = self
            .frame
            .map_or(frames - 1, |frame| frame.saturating_add(frames));
        self.frame = Some(frame);
        if let Some(time) = timestamp {
            self.last = Some((time, frame));
        }
        Ok(Tick {
            frame,
            out_of_order,
            previous,
        })
    }

    /// How far this scan's frame lies after the newest one: the frames since the last timestamped scan
    /// are at least those counted (one per scan), more when the time says more periods passed.
    fn frames_since_last(&mut self, time: f64, (last_time, last_frame): (f64, u64)) -> (u64, bool) {
        let newest = self.frame.unwrap_or(0);
        let counted = newest + 1 - last_frame;
        let interval = time - last_time;
        if interval <= 0.0 {
            return (1, true);
        }
        let frames = match self.period() {
            None => counted,
            // Half-way rounds to even.
            Some(period) => {
                counted.max((interval / period).round_ties_even().min(u64::MAX as f64) as u64)
            }
        };
        if frames == 1 {
            // Only intervals between consecutive scans measure the period.
            if self.intervals.len() == RECENT_INTERVALS {
                self.intervals.pop_front();
            }
            self.intervals.push_back(interval);
        }
        (last_frame.saturating_add(frames) - newest, false)
    }
}
