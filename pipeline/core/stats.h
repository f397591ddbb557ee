// Summary statistics of one figure across views (the study's Figure 7: mean,
// range and coefficient of variation of the 2D figures).
#pragma once

#include <cstddef>
#include <vector>

namespace aggscan {

/// Summary statistics of one figure across views. std is the SAMPLE standard
/// deviation (n-1 denominator; 0 for n < 2); cov = std / mean (0 when mean is 0).
struct Stats {
  double mean = 0;
  double min = 0;
  double max = 0;
  double std = 0;
  double cov = 0;
  int n = 0;
};

/// Stats over `values`; all zero (n = 0) for an empty vector.
Stats ComputeStats(const std::vector<double>& values);

/// The median: the middle value, the mean of the two middle ones for an even
/// count; 0 for an empty vector.
double Median(std::vector<double> values);

/// Robust outliers above: the indices of the values more than `mads` scaled
/// median absolute deviations above the median and above `floor` (so a set of
/// near-identical good values, whose MAD is almost 0, flags nothing).
std::vector<std::size_t> HighOutliers(const std::vector<double>& values, double floor,
                                      double mads = 5.0);

}  // namespace aggscan
