#include "pipeline/core/stats.h"

#include <algorithm>
#include <cmath>

namespace aggscan {

Stats ComputeStats(const std::vector<double>& values) {
  Stats s;
  s.n = static_cast<int>(values.size());
  if (values.empty()) return s;
  s.min = *std::min_element(values.begin(), values.end());
  s.max = *std::max_element(values.begin(), values.end());
  double sum = 0;
  for (double v : values) sum += v;
  s.mean = sum / s.n;
  if (s.n >= 2) {
    double ss = 0;
    for (double v : values) ss += (v - s.mean) * (v - s.mean);
    s.std = std::sqrt(ss / (s.n - 1));
  }
  s.cov = s.mean != 0 ? s.std / s.mean : 0.0;
  return s;
}

double Median(std::vector<double> v) {
  if (v.empty()) return 0;
  std::sort(v.begin(), v.end());
  const size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

std::vector<std::size_t> HighOutliers(const std::vector<double>& v, double floor, double mads) {
  const double med = Median(v);
  std::vector<double> dev;
  dev.reserve(v.size());
  for (double x : v) dev.push_back(std::abs(x - med));
  const double mad = 1.4826 * Median(dev);
  std::vector<size_t> out;
  for (size_t i = 0; i < v.size(); ++i) {
    if (v[i] > med + mads * mad && v[i] > floor) out.push_back(i);
  }
  return out;
}

}  // namespace aggscan
