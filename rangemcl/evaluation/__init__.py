"""The paper's metrics of a localization run against ground truth (``metrics``): success, location and
yaw RMSE, frames to converge, wrong convergences and false alarms."""
