"""What was measured: deposit profiles, front histories, scaling laws, flow rules and h_stop read from files,
validated, and the shipped data (``jaxmpm.datasets``' finder, re-exported: ``list_datasets``, ``dataset_path``,
``data_dir``)."""

from jaxmpm.datasets import DatasetInfo, data_dir, dataset_path, list_datasets

from .collapse import FitSpec, FrontMeasurement, Measurements, ProfileMeasurement, read_measurements, with_measurements
from .flow_rule import FlowRuleTable, HStopTable, load_flow_rule, load_h_stop
from .loaders import FrontHistory, Profile, RunoutLaw, load_front_history, load_profile, load_scaling_law
from .measurements import check_run_status, data_end_time, load_data, load_measurements, load_setup

__all__ = ["DatasetInfo", "FitSpec", "FlowRuleTable", "FrontHistory", "FrontMeasurement", "HStopTable", "Measurements",
           "Profile", "ProfileMeasurement", "RunoutLaw", "check_run_status", "data_dir", "data_end_time",
           "dataset_path", "list_datasets", "load_data", "load_flow_rule", "load_front_history", "load_h_stop",
           "load_measurements", "load_profile", "load_scaling_law", "load_setup", "read_measurements",
           "with_measurements"]
