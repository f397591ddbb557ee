// Summary statistics of one figure across views (the study's Figure 7: mean,
// range and coefficient of variation of the 2D figures).
#pragma once

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

}  // namespace aggscan
